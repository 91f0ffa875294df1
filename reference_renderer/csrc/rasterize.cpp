// Tile-based Gaussian compositing on the CPU: binning, forward and backward.
//
// This is the compiled fast path of reference_renderer (see _cpp.py for how it is built and
// called). It implements only the per-pixel part of image formation; projection, spherical
// harmonics and culling happen in PyTorch (projection.py), so autograd handles them and this file
// stays small. The pure-PyTorch path in rasterize_torch.py implements the same rules and the tests
// compare the two.
//
// Rules (DESIGN.md, "Image formation"): per pixel, the Gaussians of its tile front to back;
// sigma = 0.5 * d^T conic d with d = mean2d - pixel centre; skip when sigma < 0;
// alpha = min(0.999, o * exp(-sigma)); skip when alpha < 1/255; stop before the Gaussian that
// would take the transmittance below 1e-4; background weighted by the final transmittance.
//
// Plain C ABI (called through ctypes) so it builds in seconds with any C++17 compiler and does
// not depend on the ABI of the installed torch. All arrays are contiguous, row-major.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

namespace {

// Runs fn(item, thread_index) for item in [0, n) on n_threads threads, handing out items
// dynamically: tiles differ a lot in cost, so a static split would leave a core idle.
template <typename Fn>
void parallel_for(int64_t n, int n_threads, Fn&& fn) {
    n_threads = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(n_threads, n)));
    if (n_threads == 1) {
        for (int64_t i = 0; i < n; ++i) fn(i, 0);
        return;
    }
    std::atomic<int64_t> next(0);
    auto worker = [&](int tid) {
        for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i, tid);
    };
    std::vector<std::thread> pool;
    pool.reserve(n_threads - 1);
    for (int t = 1; t < n_threads; ++t) pool.emplace_back(worker, t);
    worker(0);
    for (auto& th : pool) th.join();
}

// Geometry of one image: its tiles and the pixel block of each.
struct Grid {
    int64_t width, height, tile, tiles_x, tiles_y;
    int64_t n_tiles() const { return tiles_x * tiles_y; }
};

// Smallest sigma = 0.5 d^T conic d over the box of pixel centres [x0, x1] x [y0, y1], with
// d = (u - x, v - y), plus a bound on how far a per-pixel evaluation in T may round below it.
// The quadratic is convex, so its minimum over the box is 0 when (u, v) lies inside, else on one
// of the four edges, where it is a 1D quadratic minimised in closed form.
template <typename T>
inline bool splat_misses_box(const T* q, double x0, double x1, double y0, double y1) {
    const double a = q[2], b = q[3], c = q[4], u = q[0], v = q[1];
    const double dxl = u - x1, dxh = u - x0, dyl = v - y1, dyh = v - y0;
    if (dxl <= 0 && dxh >= 0 && dyl <= 0 && dyh >= 0) return false;
    auto f = [&](double dx, double dy) { return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy; };
    auto clampd = [](double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); };
    double best = f(dxl, clampd(-b * dxl / c, dyl, dyh));
    best = std::min(best, f(dxh, clampd(-b * dxh / c, dyl, dyh)));
    best = std::min(best, f(clampd(-b * dyl / a, dxl, dxh), dyl));
    best = std::min(best, f(clampd(-b * dyh / a, dxl, dxh), dyh));
    // Rounding of the per-pixel sigma in T: its terms are at most `terms`, and d itself carries
    // an error of about eps * |position|, moved by the gradient of sigma.
    const double mx = std::max(std::abs(dxl), std::abs(dxh)), my = std::max(std::abs(dyl), std::abs(dyh));
    const double terms = 0.5 * (std::abs(a) * mx * mx + std::abs(c) * my * my) + std::abs(b) * mx * my;
    const double slope = (std::abs(a) + std::abs(b)) * mx + (std::abs(b) + std::abs(c)) * my;
    const double scale = std::max({std::abs(u), std::abs(v), x1, y1, 1.0});
    const double eps = std::numeric_limits<T>::epsilon();
    return best - 32.0 * eps * (terms + slope * scale) > double(q[6]);
}

// Per-Gaussian data of one tile, packed contiguously in depth order: the inner loops read it
// sequentially instead of gathering from [C, N, ...] arrays. Gaussians that reach no pixel
// centre of the tile with alpha >= 1/255 are dropped here (their square touches the tile but
// their ellipse does not): the image is unchanged and the per-pixel loops get shorter.
template <typename T>
struct TileSplats {
    int64_t count = 0, channels = 0;
    std::vector<T> geo;        // [count, 7]: u, v, conic a, b, c, opacity, sigma beyond which alpha < 1/255
    std::vector<T> color;      // [count, channels]
    std::vector<int64_t> slot; // [count]: position in the tile's full list (gradient slot)

    void load(const int32_t* ids, int64_t n, int64_t cam, int64_t N, int64_t D, const T* means2d,
              const T* conics, const T* opacities, const T* colors, const double box[4]) {
        channels = D;
        geo.resize(n * 7);
        color.resize(n * D);
        slot.resize(n);
        count = 0;
        for (int64_t k = 0; k < n; ++k) {
            const int64_t g = cam * N + ids[k];
            T* q = &geo[count * 7];
            q[0] = means2d[g * 2 + 0];
            q[1] = means2d[g * 2 + 1];
            q[2] = conics[g * 3 + 0];
            q[3] = conics[g * 3 + 1];
            q[4] = conics[g * 3 + 2];
            q[5] = opacities[g];
            // o * exp(-sigma) < 1/255 exactly when sigma > log(255 o). The margin keeps this a
            // pure shortcut: near the boundary the exact test below decides, as in the rules.
            q[6] = q[5] > T(0) ? std::log(T(255) * q[5]) + T(1e-3) : T(-1);
            if (splat_misses_box(q, box[0], box[1], box[2], box[3])) continue;
            std::memcpy(&color[count * D], &colors[g * D], sizeof(T) * D);
            slot[count++] = k;
        }
    }
};

template <typename T>
struct Consts {
    static constexpr T alpha_max = T(0.999);
    static constexpr T alpha_min = T(1.0 / 255.0);
    static constexpr T t_min = T(1e-4);
};

// Evaluates Gaussian k of the tile at pixel centre (px, py). Returns false when it is skipped
// (sigma < 0 or alpha < 1/255); otherwise sets alpha, the unclamped o * exp(-sigma) and d.
template <typename T>
inline bool splat_alpha(const T* q, T px, T py, T& alpha, T& raw, T& dx, T& dy) {
    dx = q[0] - px;
    dy = q[1] - py;
    const T sigma = T(0.5) * (q[2] * dx * dx + q[4] * dy * dy) + q[3] * dx * dy;
    if (sigma < T(0) || sigma > q[6]) return false;
    raw = q[5] * std::exp(-sigma);
    alpha = std::min(Consts<T>::alpha_max, raw);
    return alpha >= Consts<T>::alpha_min;
}

template <typename T>
void forward(const Grid& grid, int64_t C, int64_t N, int64_t D, const T* means2d, const T* conics,
             const T* opacities, const T* colors, const T* backgrounds, const int64_t* offsets,
             const int32_t* ids, T* out_color, T* out_trans, int32_t* out_last, int n_threads) {
    const int64_t n_tiles = grid.n_tiles();
    parallel_for(C * n_tiles, n_threads, [&](int64_t item, int) {
        const int64_t cam = item / n_tiles, t = item % n_tiles;
        const int64_t tx = t % grid.tiles_x, ty = t / grid.tiles_x;
        const int64_t begin = offsets[item], end = offsets[item + 1];
        const int64_t y_end = std::min(grid.height, (ty + 1) * grid.tile);
        const int64_t x_end = std::min(grid.width, (tx + 1) * grid.tile);
        const double box[4] = {tx * grid.tile + 0.5, x_end - 0.5, ty * grid.tile + 0.5, y_end - 0.5};
        thread_local TileSplats<T> splats;
        splats.load(ids + begin, end - begin, cam, N, D, means2d, conics, opacities, colors, box);
        std::vector<T> acc(D);
        const T* bg = backgrounds + cam * D;
        for (int64_t y = ty * grid.tile; y < y_end; ++y) {
            for (int64_t x = tx * grid.tile; x < x_end; ++x) {
                const T px = T(x) + T(0.5), py = T(y) + T(0.5);
                std::fill(acc.begin(), acc.end(), T(0));
                T trans = T(1);
                int32_t last = 0;
                for (int64_t k = 0; k < splats.count; ++k) {
                    T alpha, raw, dx, dy;
                    if (!splat_alpha(&splats.geo[k * 7], px, py, alpha, raw, dx, dy)) continue;
                    const T next = trans * (T(1) - alpha);
                    if (next < Consts<T>::t_min) break;
                    const T w = alpha * trans;
                    const T* c = &splats.color[k * D];
                    for (int64_t ch = 0; ch < D; ++ch) acc[ch] += w * c[ch];
                    trans = next;
                    last = static_cast<int32_t>(k + 1);
                }
                const int64_t pix = (cam * grid.height + y) * grid.width + x;
                for (int64_t ch = 0; ch < D; ++ch) out_color[pix * D + ch] = acc[ch] + trans * bg[ch];
                out_trans[pix] = trans;
                out_last[pix] = last;
            }
        }
    });
}

// Gradient slots per intersection (tile, Gaussian): d/du, d/dv, d/da, d/db, d/dc, d/do,
// |d/du|, |d/dv| summed over the tile's pixels, then d/dcolor. Each tile owns its slots, so
// threads never write to the same memory and the result does not depend on scheduling.
constexpr int64_t kGeoSlots = 8;

template <typename T>
void backward(const Grid& grid, int64_t C, int64_t N, int64_t D, const T* means2d, const T* conics,
              const T* opacities, const T* colors, const T* backgrounds, const int64_t* offsets,
              const int32_t* ids, const T* out_trans, const int32_t* out_last, const T* grad_color,
              const T* grad_alpha, T* isect_grads, int n_threads) {
    const int64_t n_tiles = grid.n_tiles();
    const int64_t slots = kGeoSlots + D;
    parallel_for(C * n_tiles, n_threads, [&](int64_t item, int) {
        const int64_t cam = item / n_tiles, t = item % n_tiles;
        const int64_t tx = t % grid.tiles_x, ty = t / grid.tiles_x;
        const int64_t begin = offsets[item], end = offsets[item + 1];
        if (end == begin) return;
        const int64_t y_end = std::min(grid.height, (ty + 1) * grid.tile);
        const int64_t x_end = std::min(grid.width, (tx + 1) * grid.tile);
        const double box[4] = {tx * grid.tile + 0.5, x_end - 0.5, ty * grid.tile + 0.5, y_end - 0.5};
        thread_local TileSplats<T> splats;
        splats.load(ids + begin, end - begin, cam, N, D, means2d, conics, opacities, colors, box);
        T* g_tile = isect_grads + begin * slots;
        std::fill(g_tile, g_tile + (end - begin) * slots, T(0));
        // Contributors of one pixel, front to back: index in the tile, alpha, transmittance
        // before it, whether alpha was clamped at 0.999, and d. Replaying the forward pass keeps
        // the exact transmittances (no division by 1 - alpha to walk back from the final one).
        struct Hit { int64_t k; T alpha, trans, dx, dy; bool clamped; };
        thread_local std::vector<Hit> hits;
        std::vector<T> behind(D);
        const T* bg = backgrounds + cam * D;
        for (int64_t y = ty * grid.tile; y < y_end; ++y) {
            for (int64_t x = tx * grid.tile; x < x_end; ++x) {
                const int64_t pix = (cam * grid.height + y) * grid.width + x;
                const int32_t last = out_last[pix];
                if (last == 0) continue;
                const T px = T(x) + T(0.5), py = T(y) + T(0.5);
                hits.clear();
                T trans = T(1);
                for (int64_t k = 0; k < last; ++k) {
                    T alpha, raw, dx, dy;
                    if (!splat_alpha(&splats.geo[k * 7], px, py, alpha, raw, dx, dy)) continue;
                    hits.push_back({k, alpha, trans, dx, dy, raw > Consts<T>::alpha_max});
                    trans *= T(1) - alpha;
                }
                const T final_trans = out_trans[pix];
                const T* gc = grad_color + pix * D;
                const T ga = grad_alpha[pix];
                // behind = sum over later contributors of colour * alpha * T, walked back to front.
                std::fill(behind.begin(), behind.end(), T(0));
                for (auto h = hits.rbegin(); h != hits.rend(); ++h) {
                    const T* q = &splats.geo[h->k * 7];
                    const T* c = &splats.color[h->k * D];
                    T* g = g_tile + splats.slot[h->k] * slots;
                    const T w = h->alpha * h->trans;
                    const T inv_keep = T(1) / (T(1) - h->alpha);
                    // dL/dalpha: own colour seen through T, minus what it hides behind it (the
                    // later colours and the background, both scaled by 1 / (1 - alpha)); the
                    // rendered alpha 1 - T_final grows by T_final / (1 - alpha).
                    T g_alpha = ga * final_trans * inv_keep;
                    for (int64_t ch = 0; ch < D; ++ch) {
                        g[kGeoSlots + ch] += gc[ch] * w;
                        g_alpha += gc[ch] * (c[ch] * h->trans -
                                             (behind[ch] + bg[ch] * final_trans) * inv_keep);
                        behind[ch] += c[ch] * w;
                    }
                    if (h->clamped) continue;  // alpha = 0.999 does not depend on o or sigma
                    const T g_sigma = -g_alpha * h->alpha;
                    const T gu = g_sigma * (q[2] * h->dx + q[3] * h->dy);
                    const T gv = g_sigma * (q[3] * h->dx + q[4] * h->dy);
                    g[0] += gu;
                    g[1] += gv;
                    g[2] += g_sigma * T(0.5) * h->dx * h->dx;
                    g[3] += g_sigma * h->dx * h->dy;
                    g[4] += g_sigma * T(0.5) * h->dy * h->dy;
                    g[5] += g_alpha * h->alpha / q[5];
                    g[6] += std::abs(gu);
                    g[7] += std::abs(gv);
                }
            }
        }
    });
}

// Sums the per-intersection slots into per-(camera, Gaussian) gradients. Cameras are
// independent, so they run in parallel; within a camera the order is fixed (deterministic).
template <typename T>
void reduce(const Grid& grid, int64_t C, int64_t N, int64_t D, const int64_t* offsets,
            const int32_t* ids, const T* isect_grads, T* grad_means2d, T* grad_conics,
            T* grad_opacities, T* grad_colors, T* absgrad_means2d, int n_threads) {
    const int64_t n_tiles = grid.n_tiles();
    const int64_t slots = kGeoSlots + D;
    parallel_for(C, n_threads, [&](int64_t cam, int) {
        for (int64_t i = offsets[cam * n_tiles]; i < offsets[(cam + 1) * n_tiles]; ++i) {
            const int64_t g = cam * N + ids[i];
            const T* s = isect_grads + i * slots;
            grad_means2d[g * 2 + 0] += s[0];
            grad_means2d[g * 2 + 1] += s[1];
            grad_conics[g * 3 + 0] += s[2];
            grad_conics[g * 3 + 1] += s[3];
            grad_conics[g * 3 + 2] += s[4];
            grad_opacities[g] += s[5];
            absgrad_means2d[g * 2 + 0] += s[6];
            absgrad_means2d[g * 2 + 1] += s[7];
            for (int64_t ch = 0; ch < D; ++ch) grad_colors[g * D + ch] += s[kGeoSlots + ch];
        }
    });
}

}  // namespace

extern "C" {

// Counts the intersections of each (camera, tile) and writes their prefix sums to
// offsets [C * tiles + 1]; returns the total. rects [C, N, 4] = x0, x1, y0, y1 (half-open,
// already clamped to the grid; empty for culled Gaussians).
int64_t mvgs_bin_count(int64_t C, int64_t N, int64_t tiles_x, int64_t tiles_y,
                       const int32_t* rects, int64_t* offsets) {
    const int64_t n_tiles = tiles_x * tiles_y;
    std::fill(offsets, offsets + C * n_tiles + 1, int64_t(0));
    for (int64_t cam = 0; cam < C; ++cam) {
        for (int64_t n = 0; n < N; ++n) {
            const int32_t* r = rects + (cam * N + n) * 4;
            for (int64_t ty = r[2]; ty < r[3]; ++ty)
                for (int64_t tx = r[0]; tx < r[1]; ++tx) ++offsets[cam * n_tiles + ty * tiles_x + tx + 1];
        }
    }
    for (int64_t i = 0; i < C * n_tiles; ++i) offsets[i + 1] += offsets[i];
    return offsets[C * n_tiles];
}

// Fills ids with the Gaussian indices of each (camera, tile) in depth order: order [C, N] lists
// each camera's Gaussians front to back, so a counting sort keeps that order within every tile.
void mvgs_bin_fill(int64_t C, int64_t N, int64_t tiles_x, int64_t tiles_y, const int32_t* rects,
                   const int64_t* order, const int64_t* offsets, int32_t* ids) {
    const int64_t n_tiles = tiles_x * tiles_y;
    std::vector<int64_t> cursor(offsets, offsets + C * n_tiles);
    for (int64_t cam = 0; cam < C; ++cam) {
        for (int64_t k = 0; k < N; ++k) {
            const int64_t n = order[cam * N + k];
            const int32_t* r = rects + (cam * N + n) * 4;
            for (int64_t ty = r[2]; ty < r[3]; ++ty)
                for (int64_t tx = r[0]; tx < r[1]; ++tx)
                    ids[cursor[cam * n_tiles + ty * tiles_x + tx]++] = static_cast<int32_t>(n);
        }
    }
}

#define MVGS_DEFINE(T, SUFFIX)                                                                    \
    void mvgs_forward_##SUFFIX(int64_t C, int64_t N, int64_t D, int64_t width, int64_t height,     \
                               int64_t tile, const T* means2d, const T* conics, const T* opacities, \
                               const T* colors, const T* backgrounds, const int64_t* offsets,      \
                               const int32_t* ids, T* out_color, T* out_trans, int32_t* out_last,  \
                               int n_threads) {                                                    \
        const Grid grid{width, height, tile, (width + tile - 1) / tile, (height + tile - 1) / tile}; \
        forward<T>(grid, C, N, D, means2d, conics, opacities, colors, backgrounds, offsets, ids,    \
                   out_color, out_trans, out_last, n_threads);                                     \
    }                                                                                              \
    void mvgs_backward_##SUFFIX(int64_t C, int64_t N, int64_t D, int64_t width, int64_t height,    \
                                int64_t tile, const T* means2d, const T* conics,                    \
                                const T* opacities, const T* colors, const T* backgrounds,          \
                                const int64_t* offsets, const int32_t* ids, const T* out_trans,     \
                                const int32_t* out_last, const T* grad_color, const T* grad_alpha,  \
                                T* isect_grads, T* grad_means2d, T* grad_conics,                    \
                                T* grad_opacities, T* grad_colors, T* absgrad_means2d,              \
                                int n_threads) {                                                   \
        const Grid grid{width, height, tile, (width + tile - 1) / tile, (height + tile - 1) / tile}; \
        backward<T>(grid, C, N, D, means2d, conics, opacities, colors, backgrounds, offsets, ids,   \
                    out_trans, out_last, grad_color, grad_alpha, isect_grads, n_threads);          \
        reduce<T>(grid, C, N, D, offsets, ids, isect_grads, grad_means2d, grad_conics,              \
                  grad_opacities, grad_colors, absgrad_means2d, n_threads);                        \
    }

MVGS_DEFINE(float, f32)
MVGS_DEFINE(double, f64)

#undef MVGS_DEFINE

}  // extern "C"
