// Fused CPU kernels of the position-based-fluid solver (fluidcore.physics), C++17 + OpenMP.
//
// The torch reference is fluidcore/physics/{neighbours,sph,solver}.py; these loops compute the
// same quantities in the same order over the same CSR neighbour list, so the two paths agree
// to float rounding. Units: density is dimensionless, W(r) = POLY6 (1 - q^2)^3 with q = r/h,
// |grad W| = SPIKY_GRAD (1 - q)^2 / h (see fluidcore/physics/sph.py for why).
//
// Neighbour lists are built in two passes over the cell table made by torch (keys sorted,
// occupied cells only): count, then fill at the offsets the caller allocated.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr float kPoly6 = float(315.0 / (512.0 * kPi));
constexpr float kSpikyGrad = float(45.0 / (8.0 * kPi));
constexpr float kCoincident = 1.0e-6f;
constexpr int kAxisBits = 21;
constexpr int64_t kAxisCells = int64_t(1) << kAxisBits;
constexpr int64_t kAxisMask = kAxisCells - 1;
constexpr double kR3[3] = {0.8191725133961645, 0.6710436067037893, 0.5497004779019703};

struct Range {
    int64_t begin, end;
};

// Particle ranges of the occupied cells around the cell with key `key` (occupied or not), one
// per (dx, dy) column: cells (x, y, z - 1), (x, y, z), (x, y, z + 1) have consecutive keys, so
// their particles are contiguous in cell order and one binary search finds all three.
int neighbour_columns(const int64_t* keys, const int64_t* start, int64_t n_cells, int64_t key, Range* out) {
    const int64_t c[3] = {key >> (2 * kAxisBits), (key >> kAxisBits) & kAxisMask, key & kAxisMask};
    const int64_t z_lo = std::max<int64_t>(c[2] - 1, 0), z_hi = std::min<int64_t>(c[2] + 1, kAxisMask);
    const int64_t* end = keys + n_cells;
    int found = 0;
    for (int dx = -1; dx <= 1; ++dx)
        for (int dy = -1; dy <= 1; ++dy) {
            const int64_t x = c[0] + dx, y = c[1] + dy;
            if (x < 0 || y < 0 || x >= kAxisCells || y >= kAxisCells) continue;
            const int64_t column = (x << (2 * kAxisBits)) | (y << kAxisBits);
            const int64_t* first = std::lower_bound(keys, end, column | z_lo);
            const int64_t* last = first;
            while (last != end && *last <= (column | z_hi)) ++last;
            if (last != first) out[found++] = {start[first - keys], start[last - keys]};
        }
    return found;
}

// Number of particles within h of sorted slot a (itself excluded) among the slots of `ranges`.
int64_t count_within(const float* sorted, float h2, int64_t a, const Range* ranges, int n_ranges) {
    const float xa = sorted[3 * a], ya = sorted[3 * a + 1], za = sorted[3 * a + 2];
    int64_t count = 0;
    for (int r = 0; r < n_ranges; ++r) {
#pragma omp simd reduction(+ : count)
        for (int64_t b = ranges[r].begin; b < ranges[r].end; ++b) {
            const float dx = xa - sorted[3 * b], dy = ya - sorted[3 * b + 1], dz = za - sorted[3 * b + 2];
            count += (dx * dx + dy * dy + dz * dz < h2) ? 1 : 0;
        }
    }
    return count - 1;  // the particle itself is at distance 0
}

// x^n for 0 <= n < 16 by squaring, without a loop, so that loops calling it still vectorise.
inline float ipow(float x, int n) {
    float result = 1.0f;
    result *= (n & 1) ? x : 1.0f;
    x *= x;
    result *= (n & 2) ? x : 1.0f;
    x *= x;
    result *= (n & 4) ? x : 1.0f;
    x *= x;
    result *= (n & 8) ? x : 1.0f;
    return result;
}

inline float poly6(float q2) {
    const float t = std::max(1.0f - q2, 0.0f);
    return kPoly6 * t * t * t;
}

// Spiky gradient grad_i W(x_i - x_j) (dimensionless density per length), divided by rho0.
inline void spiky_gradient(const float* pos, int64_t i, int64_t j, float inv_h, float scale, float g[3], float* q2_out) {
    float r[3] = {(pos[3 * i] - pos[3 * j]) * inv_h, (pos[3 * i + 1] - pos[3 * j + 1]) * inv_h,
                  (pos[3 * i + 2] - pos[3 * j + 2]) * inv_h};
    const float q2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
    *q2_out = q2;
    float q = 0.0f;
    if (q2 < kCoincident * kCoincident) {
        // Coincident particles: a fixed direction antisymmetric in (i, j), as sph.index_directions.
        float norm2 = 0.0f;
        for (int a = 0; a < 3; ++a) {
            const double pi = double(i) * kR3[a], pj = double(j) * kR3[a];
            r[a] = float((pi - std::floor(pi)) - (pj - std::floor(pj)));
            norm2 += r[a] * r[a];
        }
        const float inv = 1.0f / std::max(std::sqrt(norm2), 1.0e-12f);
        for (float& c : r) c *= inv;
    } else {
        q = std::sqrt(q2);
        const float inv = 1.0f / q;
        for (float& c : r) c *= inv;
    }
    const float t = std::max(1.0f - q, 0.0f);
    const float magnitude = -kSpikyGrad * inv_h * t * t * scale;
    for (int a = 0; a < 3; ++a) g[a] = magnitude * r[a];
}


// One Jacobi density solve over a CSR neighbour list.
//
// constraints() (density, C, lambda) stores per pair the Poly6 weight and the factor m with
// grad W_ij / rho0 = m (x_i - x_j); correct() reuses them, so square roots and divisions are
// done once per pair and iteration, in loops the compiler vectorises. Coincident pairs (m
// undefined) are flagged per row and handled by a scalar fix-up.
//
// Only where the constraint is active is there work: without s_corr, a particle whose lambda and
// neighbours' lambdas are all zero gets no correction, and a particle whose neighbourhood did not
// move keeps its density and lambda. Skipping them gives the same numbers as recomputing, so an
// expanding, mostly under-dense plume costs little after the first iteration.
struct Solver {
    float* pos;
    const int64_t n;
    const int64_t* offsets;
    const int32_t* indices;
    const float inv_h, inv_h2, inv_rho0, epsilon, inv_w_dq, scorr_scale, grad_scale, max_correction;
    const int scorr_n;
    float* density;
    std::vector<float> lambda, residual, next, weight, factor;
    std::vector<char> coincident_row, moved;

    Solver(float* pos_, int64_t n_, const int64_t* offsets_, const int32_t* indices_, float h, float rho0,
           float relaxation, float scorr_k, int scorr_n_, float scorr_dq, float max_correction_, float* density_)
        : pos(pos_), n(n_), offsets(offsets_), indices(indices_), inv_h(1.0f / h), inv_h2(1.0f / (h * h)),
          inv_rho0(1.0f / rho0), epsilon(relaxation / (h * h)), inv_w_dq(1.0f / poly6(scorr_dq * scorr_dq)),
          scorr_scale(scorr_k * h * h), grad_scale(-kSpikyGrad / (h * h * rho0)), max_correction(max_correction_),
          scorr_n(scorr_n_), density(density_), lambda(n_), residual(n_), next(3 * n_), weight(offsets_[n_]),
          factor(offsets_[n_]), coincident_row(n_), moved(n_, 1) {}

    // Early exits: in a busy neighbourhood the first few neighbours settle it.
    bool neighbourhood_moved(int64_t i) const {
        if (moved[i]) return true;
        for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k)
            if (moved[indices[k]]) return true;
        return false;
    }

    bool neighbourhood_active(int64_t i) const {
        if (scorr_scale > 0.0f || lambda[i] != 0.0f) return true;
        for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k)
            if (lambda[indices[k]] != 0.0f) return true;
        return false;
    }

    // Density, residual and lambda of every particle; returns the sum of residuals.
    double constraints(int threads) {
        double residual_sum = 0.0;
#pragma omp parallel for schedule(dynamic, 256) num_threads(threads) reduction(+ : residual_sum)
        for (int64_t i = 0; i < n; ++i) {
            if (neighbourhood_moved(i)) constraint_row(i);
            residual_sum += residual[i];
        }
        return residual_sum;
    }

    void constraint_row(int64_t i) {
        const float xi = pos[3 * i], yi = pos[3 * i + 1], zi = pos[3 * i + 2];
        const float c2 = kCoincident * kCoincident;
        float rho = kPoly6, gx = 0.0f, gy = 0.0f, gz = 0.0f, sum_g2 = 0.0f;
        int coincident = 0;
#pragma omp simd reduction(+ : rho, gx, gy, gz, sum_g2, coincident)
        for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k) {
            const int64_t j = indices[k];
            const float dx = xi - pos[3 * j], dy = yi - pos[3 * j + 1], dz = zi - pos[3 * j + 2];
            const float q2 = (dx * dx + dy * dy + dz * dz) * inv_h2;
            const float t = std::max(1.0f - q2, 0.0f);
            const float w = kPoly6 * t * t * t;
            const float q = std::sqrt(q2);
            const float u = std::max(1.0f - q, 0.0f);
            const bool apart = q2 >= c2;
            const float m = apart ? grad_scale * u * u / q : 0.0f;
            weight[k] = w;
            factor[k] = m;
            rho += w;
            gx += m * dx, gy += m * dy, gz += m * dz;
            sum_g2 += m * m * (dx * dx + dy * dy + dz * dz);
            coincident += apart ? 0 : 1;
        }
        coincident_row[i] = coincident > 0;
        if (coincident) {  // rare: exactly overlapping particles get fixed directions
            for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k) {
                if (factor[k] != 0.0f) continue;
                float g[3], q2;
                spiky_gradient(pos, i, indices[k], inv_h, inv_rho0, g, &q2);
                gx += g[0], gy += g[1], gz += g[2];
                sum_g2 += g[0] * g[0] + g[1] * g[1] + g[2] * g[2];
            }
        }
        const float c = std::max(rho * inv_rho0 - 1.0f, 0.0f);
        density[i] = rho;
        residual[i] = c;
        lambda[i] = -c / (gx * gx + gy * gy + gz * gz + sum_g2 + epsilon);
    }

    // One Jacobi position update from the current lambdas.
    void correct(int threads) {
#pragma omp parallel for schedule(dynamic, 256) num_threads(threads)
        for (int64_t i = 0; i < n; ++i) {
            float dp[3] = {0.0f, 0.0f, 0.0f};
            if (neighbourhood_active(i)) correction_row(i, dp);
            const float norm = std::sqrt(dp[0] * dp[0] + dp[1] * dp[1] + dp[2] * dp[2]);
            const float shrink = norm > max_correction ? max_correction / norm : 1.0f;
            for (int a = 0; a < 3; ++a) next[3 * i + a] = pos[3 * i + a] + shrink * dp[a];
            moved[i] = norm > 0.0f;
        }
        std::copy(next.begin(), next.end(), pos);
    }

    void correction_row(int64_t i, float dp[3]) const {
        const float xi = pos[3 * i], yi = pos[3 * i + 1], zi = pos[3 * i + 2];
        const float li = lambda[i];
        float dx_sum = 0.0f, dy_sum = 0.0f, dz_sum = 0.0f;
        if (scorr_scale > 0.0f) {
#pragma omp simd reduction(+ : dx_sum, dy_sum, dz_sum)
            for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k) {
                const int64_t j = indices[k];
                const float s = (li + lambda[j] - scorr_scale * ipow(weight[k] * inv_w_dq, scorr_n)) * factor[k];
                dx_sum += s * (xi - pos[3 * j]), dy_sum += s * (yi - pos[3 * j + 1]), dz_sum += s * (zi - pos[3 * j + 2]);
            }
        } else {
#pragma omp simd reduction(+ : dx_sum, dy_sum, dz_sum)
            for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k) {
                const int64_t j = indices[k];
                const float s = (li + lambda[j]) * factor[k];
                dx_sum += s * (xi - pos[3 * j]), dy_sum += s * (yi - pos[3 * j + 1]), dz_sum += s * (zi - pos[3 * j + 2]);
            }
        }
        dp[0] = dx_sum, dp[1] = dy_sum, dp[2] = dz_sum;
        if (!coincident_row[i]) return;
        for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k) {
            if (factor[k] != 0.0f) continue;
            const int64_t j = indices[k];
            float g[3], q2;
            spiky_gradient(pos, i, j, inv_h, inv_rho0, g, &q2);
            float s = li + lambda[j];
            if (scorr_scale > 0.0f) s -= scorr_scale * ipow(weight[k] * inv_w_dq, scorr_n);
            dp[0] += s * g[0], dp[1] += s * g[1], dp[2] += s * g[2];
        }
    }
};

}  // namespace

extern "C" {

// Pass 1: number of neighbours of each particle; returns the total. `sorted` holds the positions
// in cell order (slot a is particle order[a]), so each column's candidates are contiguous.
int64_t pbf_count_neighbours(const float* sorted, float h, const int64_t* keys, const int64_t* start, int64_t n_cells,
                             const int64_t* order, int64_t* counts, int threads) {
    const float h2 = h * h;
    int64_t total = 0;
#pragma omp parallel for schedule(dynamic, 64) num_threads(threads) reduction(+ : total)
    for (int64_t m = 0; m < n_cells; ++m) {
        Range ranges[9];
        const int n_ranges = neighbour_columns(keys, start, n_cells, keys[m], ranges);
        for (int64_t a = start[m]; a < start[m + 1]; ++a) {
            const int64_t count = count_within(sorted, h2, a, ranges, n_ranges);
            counts[order[a]] = count;
            total += count;
        }
    }
    return total;
}

// Pass 2: neighbour indices, row i at indices[offsets[i]:offsets[i + 1]], in cell order.
// Candidates are written without branches into a scratch row (the write pointer advances only
// for a neighbour), then copied: no mispredicted branch per candidate.
void pbf_fill_neighbours(const float* sorted, float h, const int64_t* keys, const int64_t* start, int64_t n_cells,
                         const int64_t* order, const int64_t* offsets, int32_t* indices, int threads) {
    const float h2 = h * h;
#pragma omp parallel num_threads(threads)
    {
        std::vector<int32_t> scratch;
#pragma omp for schedule(dynamic, 64)
        for (int64_t m = 0; m < n_cells; ++m) {
            Range ranges[9];
            const int n_ranges = neighbour_columns(keys, start, n_cells, keys[m], ranges);
            int64_t candidates = 0;
            for (int r = 0; r < n_ranges; ++r) candidates += ranges[r].end - ranges[r].begin;
            scratch.resize(candidates);
            for (int64_t a = start[m]; a < start[m + 1]; ++a) {
                const float xa = sorted[3 * a], ya = sorted[3 * a + 1], za = sorted[3 * a + 2];
                int64_t found = 0;
                for (int r = 0; r < n_ranges; ++r)
                    for (int64_t b = ranges[r].begin; b < ranges[r].end; ++b) {
                        const float dx = xa - sorted[3 * b], dy = ya - sorted[3 * b + 1], dz = za - sorted[3 * b + 2];
                        scratch[found] = int32_t(order[b]);
                        found += (b != a) & (dx * dx + dy * dy + dz * dz < h2);
                    }
                std::copy(scratch.begin(), scratch.begin() + found, indices + offsets[order[a]]);
            }
        }
    }
}

// Density of every particle (self term included) over a CSR neighbour list.
void pbf_density(const float* pos, int64_t n, float h, const int64_t* offsets, const int32_t* indices, float* density,
                 int threads) {
    const float inv_h2 = 1.0f / (h * h);
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        float rho = kPoly6;
        for (int64_t k = offsets[i]; k < offsets[i + 1]; ++k) {
            const int64_t j = indices[k];
            const float dx = pos[3 * i] - pos[3 * j], dy = pos[3 * i + 1] - pos[3 * j + 1],
                        dz = pos[3 * i + 2] - pos[3 * j + 2];
            rho += poly6((dx * dx + dy * dy + dz * dz) * inv_h2);
        }
        density[i] = rho;
    }
}

// Shepard (normalised Poly6) average of point values at query points: out[q] = sum_p W v_p / sum_p W
// over the points within h of query q, 0 where there is none. Points are given in cell order
// (`sorted_points`, `sorted_values`: slot a of the cell table); `query_keys` are the cells of the
// queries in the same grid, clamped into it, so a far query still gets exact distances.
void pbf_interpolate(const float* query, const int64_t* query_keys, int64_t n_query, const float* sorted_points,
                     const float* sorted_values, float h, const int64_t* keys, const int64_t* start, int64_t n_cells,
                     float* out, int threads) {
    const float inv_h2 = 1.0f / (h * h);
#pragma omp parallel for schedule(dynamic, 64) num_threads(threads)
    for (int64_t q = 0; q < n_query; ++q) {
        Range ranges[9];
        const int n_ranges = neighbour_columns(keys, start, n_cells, query_keys[q], ranges);
        const float xq = query[3 * q], yq = query[3 * q + 1], zq = query[3 * q + 2];
        float total = 0.0f, vx = 0.0f, vy = 0.0f, vz = 0.0f;
        for (int r = 0; r < n_ranges; ++r) {
#pragma omp simd reduction(+ : total, vx, vy, vz)
            for (int64_t b = ranges[r].begin; b < ranges[r].end; ++b) {
                const float dx = xq - sorted_points[3 * b], dy = yq - sorted_points[3 * b + 1],
                            dz = zq - sorted_points[3 * b + 2];
                const float w = poly6((dx * dx + dy * dy + dz * dz) * inv_h2);
                total += w;
                vx += w * sorted_values[3 * b], vy += w * sorted_values[3 * b + 1], vz += w * sorted_values[3 * b + 2];
            }
        }
        const float inv = 1.0f / std::max(total, 1.0e-12f);
        out[3 * q] = vx * inv, out[3 * q + 1] = vy * inv, out[3 * q + 2] = vz * inv;
    }
}

// Jacobi PBF density solve, one-sided constraint C_i = max(0, rho_i / rho0 - 1), in place on pos.
// Runs `max_iterations` iterations, or fewer when tolerance > 0 and the mean residual drops below
// it. On return `density` holds the density of the returned positions; returns iterations used.
int pbf_solve(float* pos, int64_t n, const int64_t* offsets, const int32_t* indices, float h, float rho0,
              float relaxation, float scorr_k, int scorr_n, float scorr_dq, float max_correction, int max_iterations,
              float tolerance, float* density, int threads) {
    Solver solver(pos, n, offsets, indices, h, rho0, relaxation, scorr_k, scorr_n, scorr_dq, max_correction, density);
    int iteration = 0;
    for (;; ++iteration) {
        const double residual_sum = solver.constraints(threads);
        const bool converged = tolerance > 0.0f && n > 0 && residual_sum / double(n) < tolerance;
        if (iteration == max_iterations || converged || n == 0) break;
        solver.correct(threads);
    }
    return iteration;
}

}  // extern "C"
