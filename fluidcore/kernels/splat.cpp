// Fused CPU compositor for tile-binned 2D Gaussians: forward and backward of front-to-back
// alpha blending (the torch reference is fluidcore/render/rasterize.py::composite_reference).
//
// Loop order: for each 16x16 tile (OpenMP threads take tiles), for each Gaussian of the tile's
// front-to-back list, for each tile row its screen box covers, all 16 pixels of the row as one
// SIMD loop. The per-pixel state (transmittance, accumulated features, where the pixel stopped)
// lives in small tile arrays. Smoke Gaussians are small, so skipping the rows outside a
// Gaussian's box avoids much of the work of a pixel-major loop over all of a tile's (pixel,
// Gaussian) pairs, while full 16-pixel rows give the vectoriser fixed-length, branch-free loops
// (pixels outside the box fail the alpha test like any other). The backward pass sums one
// Gaussian's gradient over the tile in registers before writing it.
//
// Per-pixel rules (gsplat's classic mode, so both backends draw the same picture):
//   alpha = min(0.999, opacity * exp(-sigma)); a pixel skips a Gaussian when alpha < 1/255;
//   a pixel stops before the Gaussian that would take its transmittance to <= 1e-4.
// The forward pass records, per pixel, the final transmittance and the list position where it
// stopped; the backward pass walks each tile's list back to front, recovering the transmittance
// in front of every Gaussian by division (alpha <= 0.999 keeps that well conditioned).
//
// Gradient accumulation: per-thread buffers, not atomics. Each thread owns an N x (6 + F) slice
// of `grad_buffers` (zeroed by the caller, summed over threads by the caller). A float atomic
// add on x86 is a compare-and-swap loop; per-thread buffers cost threads x N x (6 + F) floats
// (2 x 100k x 10 x 4 B = 8 MB here) and keep the sums free of contention.

#include <omp.h>

// Without these, GCC keeps the per-pixel min/select code below as branches instead of SIMD
// blends (it must preserve FP exception flags, signed zeros and NaN ordering). None of that is
// observable here: inputs are checked finite in Python, exp_neg's argument is clamped and
// 1 - alpha >= 0.001, so every value stays finite.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("no-trapping-math", "no-signed-zeros", "finite-math-only")
#endif

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace {

constexpr int kTile = 16;  // must match fluidcore.render.tiles.TILE_SIZE
constexpr int kTilePixels = kTile * kTile;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.999f;
constexpr float kTransmittanceMin = 1e-4f;
constexpr float kSigmaCut = 6.0f;  // > ln 255 = 5.54: beyond it alpha < 1/255 for any opacity <= 1
constexpr int kGradStride = 6;     // d mean x, d mean y, d conic a, b, c, d opacity; then F features

struct Scene {
    int width, height, tiles_x;
    const int32_t* offsets;   // (tiles + 1,) CSR offsets into ids
    const int32_t* ids;       // Gaussian index per (tile, Gaussian) pair, front to back per tile
    const float* means2d;     // (N, 2)
    const float* conics;      // (N, 3)
    const float* opacities;   // (N,)
    const float* features;    // (N, F)
    const int32_t* bboxes;    // (N, 4) x0, x1, y0, y1, half-open, inside the image
};

// e^-sigma, branch-free so that the pixel loops vectorise (std::exp does not without
// -ffast-math). Cody-Waite reduction by ln 2 and Cephes' degree-6 polynomial for expf (within
// 2 ulp). sigma is clamped to [0, kSigmaCut]: a pixel beyond the cut never reaches alpha >= 1/255,
// so the clamped value only reaches masked-out lanes, and the clamp keeps those lanes clear of
// subnormal floats (about a hundred cycles per operation).
inline float exp_neg(float sigma) {
    const float x = -std::min(std::max(sigma, 0.0f), kSigmaCut);
    const float n = static_cast<float>(static_cast<int32_t>(x * 1.44269504f - 0.5f));  // round(x / ln 2)
    const float r = x - n * 0.693359375f + n * 2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;  // 2^n
    float scale;
    std::memcpy(&scale, &bits, sizeof scale);
    return p * scale;
}

// One Gaussian's screen-space parameters, loaded once per (tile, Gaussian) pair.
struct Splat {
    float mx, my, a, b, c, opacity;
    Splat(const Scene& s, int g)
        : mx(s.means2d[2 * g]), my(s.means2d[2 * g + 1]), a(s.conics[3 * g]), b(s.conics[3 * g + 1]),
          c(s.conics[3 * g + 2]), opacity(s.opacities[g]) {}
    // sigma = 0.5 (a dx^2 + c dy^2) + b dx dy, with (dx, dy) = mean - pixel centre.
    float sigma(float dx, float dy) const { return 0.5f * (a * dx * dx + c * dy * dy) + b * dx * dy; }
};

// A tile's position and the rows [y0, y1) of it that lie inside the image.
struct Tile {
    int x0, y0, y1, begin, count;
    Tile(const Scene& s, int tile)
        : x0((tile % s.tiles_x) * kTile), y0((tile / s.tiles_x) * kTile),
          y1(std::min(y0 + kTile, s.height)), begin(s.offsets[tile]), count(s.offsets[tile + 1] - begin) {}
    int x1(const Scene& s) const { return std::min(x0 + kTile, s.width); }
    // Rows of the tile that Gaussian g's box covers (empty when the box misses the tile in x).
    void rows(const Scene& s, int g, int& first, int& last) const {
        const int32_t* box = s.bboxes + 4 * g;
        const bool misses = box[1] <= x0 || box[0] >= x0 + kTile;
        first = std::max(y0, box[2]);
        last = misses ? first : std::min(y1, box[3]);
    }
};

// Each row is processed in SIMD passes over its 16 pixels: one for alpha and transmittance,
// then one per feature channel, so a grey image does a third of the channel work of RGB.
template <int F>
void forward_tile(const Scene& s, int tile_id, float* out_features, float* out_transmittance, int32_t* out_stop) {
    const Tile t(s, tile_id);
    alignas(64) float transmittance[kTilePixels];
    alignas(64) float acc[F][kTilePixels];
    alignas(64) int32_t stop[kTilePixels];  // list position of the Gaussian that would saturate the pixel
    std::fill_n(transmittance, kTilePixels, 1.0f);
    for (int c = 0; c < F; ++c) std::fill_n(acc[c], kTilePixels, 0.0f);
    std::fill_n(stop, kTilePixels, t.count);
    int n_done = 0;  // saturated pixels; the tile is finished when all of them are

    for (int k = 0; k < t.count && n_done < kTilePixels; ++k) {
        const int g = s.ids[t.begin + k];
        int first, last;
        t.rows(s, g, first, last);
        const Splat q(s, g);
        const float* f = s.features + F * g;
        for (int y = first; y < last; ++y) {
            const float dy = q.my - (static_cast<float>(y) + 0.5f);
            float* const T = transmittance + (y - t.y0) * kTile;
            int32_t* const stop_row = stop + (y - t.y0) * kTile;
            alignas(64) float weight[kTile];
#pragma omp simd reduction(+ : n_done)
            for (int i = 0; i < kTile; ++i) {
                const float dx = q.mx - (static_cast<float>(t.x0 + i) + 0.5f);
                const float sigma = q.sigma(dx, dy);
                const float alpha = std::min(kAlphaMax, q.opacity * exp_neg(sigma));
                const bool counted = (stop_row[i] == t.count) & (sigma >= 0.0f) & (alpha >= kAlphaMin);
                const float next = T[i] * (1.0f - alpha);
                const bool ends = counted & (next <= kTransmittanceMin);
                const bool blends = counted & !ends;
                weight[i] = (blends ? alpha : 0.0f) * T[i];
                T[i] = blends ? next : T[i];
                const int32_t ends_mask = -static_cast<int32_t>(ends);  // bit blend: a select GCC vectorises
                stop_row[i] = (k & ends_mask) | (stop_row[i] & ~ends_mask);
                n_done += static_cast<int>(ends);
            }
            for (int c = 0; c < F; ++c) {
                float* const out = acc[c] + (y - t.y0) * kTile;
                const float fc = f[c];
#pragma omp simd
                for (int i = 0; i < kTile; ++i) out[i] += weight[i] * fc;
            }
        }
    }

    // Columns right of the image were computed but are not written.
    for (int y = t.y0; y < t.y1; ++y) {
        for (int x = t.x0; x < t.x1(s); ++x) {
            const int p = (y - t.y0) * kTile + (x - t.x0);
            const int64_t pixel = static_cast<int64_t>(y) * s.width + x;
            for (int c = 0; c < F; ++c) out_features[pixel * F + c] = acc[c][p];
            out_transmittance[pixel] = transmittance[p];
            out_stop[pixel] = stop[p];
        }
    }
}

template <int F>
void backward_tile(const Scene& s, int tile_id, const float* final_transmittance, const int32_t* pixel_stop,
                   const float* grad_features, const float* grad_transmittance, float* grads) {
    const Tile t(s, tile_id);
    // Per pixel: transmittance behind the current Gaussian, the features composited behind it
    // divided by that transmittance, and the incoming gradients. Pixels outside the image keep
    // stop = 0, so no Gaussian counts there.
    alignas(64) float transmittance[kTilePixels];
    alignas(64) float behind[F][kTilePixels];
    alignas(64) float g_feat[F][kTilePixels];
    alignas(64) float g_final[kTilePixels];  // dL/dT_final * T_final
    alignas(64) int32_t stop[kTilePixels];
    std::fill_n(transmittance, kTilePixels, 1.0f);
    std::fill_n(g_final, kTilePixels, 0.0f);
    std::fill_n(stop, kTilePixels, 0);
    for (int c = 0; c < F; ++c) {
        std::fill_n(behind[c], kTilePixels, 0.0f);
        std::fill_n(g_feat[c], kTilePixels, 0.0f);
    }
    for (int y = t.y0; y < t.y1; ++y) {
        for (int x = t.x0; x < t.x1(s); ++x) {
            const int p = (y - t.y0) * kTile + (x - t.x0);
            const int64_t pixel = static_cast<int64_t>(y) * s.width + x;
            transmittance[p] = final_transmittance[pixel];
            g_final[p] = grad_transmittance[pixel] * final_transmittance[pixel];
            stop[p] = pixel_stop[pixel];
            for (int c = 0; c < F; ++c) g_feat[c][p] = grad_features[pixel * F + c];
        }
    }

    for (int k = t.count - 1; k >= 0; --k) {
        const int g = s.ids[t.begin + k];
        int first, last;
        t.rows(s, g, first, last);
        if (first >= last) continue;
        const Splat q(s, g);
        const float* f = s.features + F * g;
        float d_mx = 0, d_my = 0, d_a = 0, d_b = 0, d_c = 0, d_opacity = 0;
        float d_f[F] = {};
        for (int y = first; y < last; ++y) {
            const int row = (y - t.y0) * kTile;
            const float dy = q.my - (static_cast<float>(y) + 0.5f);
            float* const T = transmittance + row;
            // Pass 1: alpha of this Gaussian per pixel, and the transmittance in front of it.
            alignas(64) float falloff[kTile], alpha[kTile], keep[kTile], t_front[kTile], counted[kTile];
#pragma omp simd
            for (int i = 0; i < kTile; ++i) {
                const float dx = q.mx - (static_cast<float>(t.x0 + i) + 0.5f);
                const float sigma = q.sigma(dx, dy);
                falloff[i] = exp_neg(sigma);
                alpha[i] = std::min(kAlphaMax, q.opacity * falloff[i]);
                const bool in = (k < stop[row + i]) & (sigma >= 0.0f) & (alpha[i] >= kAlphaMin);
                counted[i] = in ? 1.0f : 0.0f;
                keep[i] = 1.0f - alpha[i];
                t_front[i] = T[i] / keep[i];
                T[i] = in ? t_front[i] : T[i];
            }
            // Pass 2, per channel: colour gradients, and dL/dalpha's share from what lies behind.
            alignas(64) float d_alpha[kTile] = {};
            for (int c = 0; c < F; ++c) {
                float* const bc = behind[c] + row;
                const float* const gc = g_feat[c] + row;
                const float fc = f[c];
                float sum = 0.0f;
#pragma omp simd reduction(+ : sum)
                for (int i = 0; i < kTile; ++i) {
                    sum += counted[i] * alpha[i] * t_front[i] * gc[i];
                    d_alpha[i] += (fc - bc[i]) * gc[i];
                    bc[i] = counted[i] > 0.0f ? bc[i] * keep[i] + fc * alpha[i] : bc[i];
                }
                d_f[c] += sum;
            }
            // Pass 3: through alpha = opacity * exp(-sigma) to the opacity, conic and mean.
#pragma omp simd reduction(+ : d_mx, d_my, d_a, d_b, d_c, d_opacity)
            for (int i = 0; i < kTile; ++i) {
                const float dx = q.mx - (static_cast<float>(t.x0 + i) + 0.5f);
                // Where alpha is capped it is flat in sigma and opacity.
                const bool live = (counted[i] > 0.0f) & (q.opacity * falloff[i] < kAlphaMax);
                const float grad_alpha = d_alpha[i] * t_front[i] - g_final[row + i] / keep[i];
                const float d_sigma = live ? -alpha[i] * grad_alpha : 0.0f;
                d_opacity += live ? falloff[i] * grad_alpha : 0.0f;
                d_a += 0.5f * d_sigma * dx * dx;
                d_b += d_sigma * dx * dy;
                d_c += 0.5f * d_sigma * dy * dy;
                d_mx += d_sigma * (q.a * dx + q.b * dy);
                d_my += d_sigma * (q.b * dx + q.c * dy);
            }
        }
        float* out = grads + static_cast<int64_t>(g) * (kGradStride + F);
        out[0] += d_mx;
        out[1] += d_my;
        out[2] += d_a;
        out[3] += d_b;
        out[4] += d_c;
        out[5] += d_opacity;
        for (int c = 0; c < F; ++c) out[kGradStride + c] += d_f[c];
    }
}

template <int F>
void forward_all(const Scene& s, int n_tiles, float* out_features, float* out_transmittance, int32_t* out_stop,
                 int n_threads) {
#pragma omp parallel for schedule(dynamic, 1) num_threads(n_threads)
    for (int tile = 0; tile < n_tiles; ++tile) forward_tile<F>(s, tile, out_features, out_transmittance, out_stop);
}

template <int F>
void backward_all(const Scene& s, int n_tiles, int n_gaussians, const float* final_transmittance,
                  const int32_t* stop, const float* grad_features, const float* grad_transmittance,
                  float* grad_buffers, int n_threads) {
#pragma omp parallel num_threads(n_threads)
    {
        float* mine = grad_buffers + static_cast<int64_t>(omp_get_thread_num()) * n_gaussians * (kGradStride + F);
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile)
            backward_tile<F>(s, tile, final_transmittance, stop, grad_features, grad_transmittance, mine);
    }
}

int check(int n_features, int tile_size) {
    if (n_features < 1 || n_features > 4) return -1;
    if (tile_size != kTile) return -2;
    return 0;
}

}  // namespace

extern "C" {

// Status codes: 0 ok, -1 unsupported number of features (1..4), -2 tile size other than 16.
int splat_forward(int width, int height, int tile_size, int tiles_x, int tiles_y, const int32_t* offsets,
                  const int32_t* ids, const float* means2d, const float* conics, const float* opacities,
                  const float* features, int n_features, const int32_t* bboxes, float* out_features,
                  float* out_transmittance, int32_t* out_stop, int n_threads) {
    if (int status = check(n_features, tile_size)) return status;
    const Scene s{width, height, tiles_x, offsets, ids, means2d, conics, opacities, features, bboxes};
    const int n_tiles = tiles_x * tiles_y;
    switch (n_features) {
        case 1: forward_all<1>(s, n_tiles, out_features, out_transmittance, out_stop, n_threads); break;
        case 2: forward_all<2>(s, n_tiles, out_features, out_transmittance, out_stop, n_threads); break;
        case 3: forward_all<3>(s, n_tiles, out_features, out_transmittance, out_stop, n_threads); break;
        case 4: forward_all<4>(s, n_tiles, out_features, out_transmittance, out_stop, n_threads); break;
    }
    return 0;
}

// grad_buffers: (n_threads, n_gaussians, 6 + n_features) zeros; per Gaussian d mean2d (2),
// d conic (3), d opacity, d features (F).
int splat_backward(int width, int height, int tile_size, int tiles_x, int tiles_y, const int32_t* offsets,
                   const int32_t* ids, const float* means2d, const float* conics, const float* opacities,
                   const float* features, int n_features, const int32_t* bboxes, int n_gaussians,
                   const float* final_transmittance, const int32_t* stop, const float* grad_features,
                   const float* grad_transmittance, float* grad_buffers, int n_threads) {
    if (int status = check(n_features, tile_size)) return status;
    const Scene s{width, height, tiles_x, offsets, ids, means2d, conics, opacities, features, bboxes};
    const int n_tiles = tiles_x * tiles_y;
    switch (n_features) {
        case 1: backward_all<1>(s, n_tiles, n_gaussians, final_transmittance, stop, grad_features, grad_transmittance, grad_buffers, n_threads); break;
        case 2: backward_all<2>(s, n_tiles, n_gaussians, final_transmittance, stop, grad_features, grad_transmittance, grad_buffers, n_threads); break;
        case 3: backward_all<3>(s, n_tiles, n_gaussians, final_transmittance, stop, grad_features, grad_transmittance, grad_buffers, n_threads); break;
        case 4: backward_all<4>(s, n_tiles, n_gaussians, final_transmittance, stop, grad_features, grad_transmittance, grad_buffers, n_threads); break;
    }
    return 0;
}

}  // extern "C"
