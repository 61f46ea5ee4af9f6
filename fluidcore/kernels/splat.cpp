// Fused CPU compositor for tile-binned 2D Gaussians: forward and backward of front-to-back
// alpha blending (the torch reference is fluidcore/render/rasterize.py::composite_reference).
//
// Why Gaussian-major loops: smoke Gaussians are small, so most of a 16x16 tile lies outside a
// given Gaussian's box. Visiting, for each Gaussian of the tile's front-to-back list, only the
// pixels inside its box (per-pixel transmittance kept in small tile arrays) does a fraction of
// the work of the usual pixel-major loop over every (pixel, Gaussian) pair of the tile, and lets
// the backward pass sum one Gaussian's gradient over the tile in registers before writing it.
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

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace {

constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.999f;
constexpr float kTransmittanceMin = 1e-4f;
constexpr int kMaxTileSize = 32;
constexpr int kGradStride = 6;  // d mean x, d mean y, d conic a, b, c, d opacity; then F features

struct Scene {
    int width, height, tile_size, tiles_x;
    const int32_t* offsets;   // (tiles + 1,) CSR offsets into ids
    const int32_t* ids;       // Gaussian index per (tile, Gaussian) pair, front to back per tile
    const float* means2d;     // (N, 2)
    const float* conics;      // (N, 3)
    const float* opacities;   // (N,)
    const float* features;    // (N, F)
    const int32_t* bboxes;    // (N, 4) x0, x1, y0, y1, half-open, inside the image
};

// The pixel rectangle a tile covers, clipped to the image.
struct Rect {
    int x0, x1, y0, y1;
    bool empty() const { return x0 >= x1 || y0 >= y1; }
};

Rect tile_rect(const Scene& s, int tile) {
    const int tx = tile % s.tiles_x, ty = tile / s.tiles_x;
    return {tx * s.tile_size, std::min((tx + 1) * s.tile_size, s.width),
            ty * s.tile_size, std::min((ty + 1) * s.tile_size, s.height)};
}

Rect overlap(const Rect& tile, const int32_t* box) {
    return {std::max(tile.x0, box[0]), std::min(tile.x1, box[1]),
            std::max(tile.y0, box[2]), std::min(tile.y1, box[3])};
}

// Alpha of Gaussian g at the centre of pixel (x, y). Returns false where the pixel skips it.
// Forward and backward both call this, so they agree on which pairs count.
inline bool alpha_at(const Scene& s, int g, int x, int y, float& alpha, float& falloff, float& dx, float& dy) {
    dx = s.means2d[2 * g] - (static_cast<float>(x) + 0.5f);
    dy = s.means2d[2 * g + 1] - (static_cast<float>(y) + 0.5f);
    const float* q = s.conics + 3 * g;
    const float sigma = 0.5f * (q[0] * dx * dx + q[2] * dy * dy) + q[1] * dx * dy;
    falloff = std::exp(-sigma);
    alpha = std::min(kAlphaMax, s.opacities[g] * falloff);
    return sigma >= 0.0f && alpha >= kAlphaMin;
}

template <int F>
void forward_tile(const Scene& s, int tile, float* out_features, float* out_transmittance, int32_t* out_stop) {
    const Rect rect = tile_rect(s, tile);
    const int begin = s.offsets[tile], count = s.offsets[tile + 1] - begin;
    const int stride = s.tile_size;
    float transmittance[kMaxTileSize * kMaxTileSize];
    float acc[kMaxTileSize * kMaxTileSize * F];
    int32_t stop[kMaxTileSize * kMaxTileSize];
    std::fill_n(transmittance, stride * stride, 1.0f);
    std::fill_n(acc, stride * stride * F, 0.0f);
    std::fill_n(stop, stride * stride, count);
    const int n_pixels = (rect.x1 - rect.x0) * (rect.y1 - rect.y0);
    int n_done = 0;

    for (int k = 0; k < count && n_done < n_pixels; ++k) {
        const int g = s.ids[begin + k];
        const Rect r = overlap(rect, s.bboxes + 4 * g);
        if (r.empty()) continue;
        const float* f = s.features + F * g;
        for (int y = r.y0; y < r.y1; ++y) {
            for (int x = r.x0; x < r.x1; ++x) {
                const int p = (y - rect.y0) * stride + (x - rect.x0);
                if (stop[p] != count) continue;  // this pixel is already opaque
                float alpha, falloff, dx, dy;
                if (!alpha_at(s, g, x, y, alpha, falloff, dx, dy)) continue;
                const float next = transmittance[p] * (1.0f - alpha);
                if (next <= kTransmittanceMin) {
                    stop[p] = k;
                    ++n_done;
                    continue;
                }
                const float weight = alpha * transmittance[p];
                for (int c = 0; c < F; ++c) acc[p * F + c] += weight * f[c];
                transmittance[p] = next;
            }
        }
    }

    for (int y = rect.y0; y < rect.y1; ++y) {
        for (int x = rect.x0; x < rect.x1; ++x) {
            const int p = (y - rect.y0) * stride + (x - rect.x0);
            const int64_t pixel = static_cast<int64_t>(y) * s.width + x;
            for (int c = 0; c < F; ++c) out_features[pixel * F + c] = acc[p * F + c];
            out_transmittance[pixel] = transmittance[p];
            out_stop[pixel] = stop[p];
        }
    }
}

template <int F>
void backward_tile(const Scene& s, int tile, const float* final_transmittance, const int32_t* pixel_stop,
                   const float* grad_features, const float* grad_transmittance, float* grads) {
    const Rect rect = tile_rect(s, tile);
    const int begin = s.offsets[tile], count = s.offsets[tile + 1] - begin;
    const int stride = s.tile_size;
    // Per pixel: transmittance behind the current Gaussian, features composited behind it
    // divided by that transmittance, and the incoming gradients.
    float transmittance[kMaxTileSize * kMaxTileSize];
    float behind[kMaxTileSize * kMaxTileSize * F];
    float g_feat[kMaxTileSize * kMaxTileSize * F];
    float g_final[kMaxTileSize * kMaxTileSize];  // dL/dT_final * T_final
    int32_t stop[kMaxTileSize * kMaxTileSize];
    for (int y = rect.y0; y < rect.y1; ++y) {
        for (int x = rect.x0; x < rect.x1; ++x) {
            const int p = (y - rect.y0) * stride + (x - rect.x0);
            const int64_t pixel = static_cast<int64_t>(y) * s.width + x;
            transmittance[p] = final_transmittance[pixel];
            g_final[p] = grad_transmittance[pixel] * final_transmittance[pixel];
            stop[p] = pixel_stop[pixel];
            for (int c = 0; c < F; ++c) {
                behind[p * F + c] = 0.0f;
                g_feat[p * F + c] = grad_features[pixel * F + c];
            }
        }
    }

    for (int k = count - 1; k >= 0; --k) {
        const int g = s.ids[begin + k];
        const Rect r = overlap(rect, s.bboxes + 4 * g);
        if (r.empty()) continue;
        const float* f = s.features + F * g;
        const float* q = s.conics + 3 * g;
        const float opacity = s.opacities[g];
        float d_mx = 0, d_my = 0, d_a = 0, d_b = 0, d_c = 0, d_opacity = 0;
        float d_f[F] = {};
        for (int y = r.y0; y < r.y1; ++y) {
            for (int x = r.x0; x < r.x1; ++x) {
                const int p = (y - rect.y0) * stride + (x - rect.x0);
                if (k >= stop[p]) continue;
                float alpha, falloff, dx, dy;
                if (!alpha_at(s, g, x, y, alpha, falloff, dx, dy)) continue;
                const float keep = 1.0f - alpha;
                const float t_front = transmittance[p] / keep;
                const float weight = alpha * t_front;
                float d_alpha = 0.0f;
                for (int c = 0; c < F; ++c) {
                    const float gc = g_feat[p * F + c];
                    d_f[c] += weight * gc;
                    d_alpha += (f[c] - behind[p * F + c]) * gc;
                    behind[p * F + c] = behind[p * F + c] * keep + f[c] * alpha;
                }
                d_alpha = d_alpha * t_front - g_final[p] / keep;
                transmittance[p] = t_front;
                if (opacity * falloff >= kAlphaMax) continue;  // alpha is clamped: flat in sigma and opacity
                d_opacity += falloff * d_alpha;
                const float d_sigma = -alpha * d_alpha;
                d_a += 0.5f * d_sigma * dx * dx;
                d_b += d_sigma * dx * dy;
                d_c += 0.5f * d_sigma * dy * dy;
                d_mx += d_sigma * (q[0] * dx + q[1] * dy);
                d_my += d_sigma * (q[1] * dx + q[2] * dy);
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
    if (tile_size < 1 || tile_size > kMaxTileSize) return -2;
    return 0;
}

}  // namespace

extern "C" {

// Status codes: 0 ok, -1 unsupported number of features (1..4), -2 tile size outside 1..32.
int splat_forward(int width, int height, int tile_size, int tiles_x, int tiles_y, const int32_t* offsets,
                  const int32_t* ids, const float* means2d, const float* conics, const float* opacities,
                  const float* features, int n_features, const int32_t* bboxes, float* out_features,
                  float* out_transmittance, int32_t* out_stop, int n_threads) {
    if (int status = check(n_features, tile_size)) return status;
    const Scene s{width, height, tile_size, tiles_x, offsets, ids, means2d, conics, opacities, features, bboxes};
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
    const Scene s{width, height, tile_size, tiles_x, offsets, ids, means2d, conics, opacities, features, bboxes};
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
