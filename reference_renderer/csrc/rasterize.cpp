// Tile-based Gaussian compositing on the CPU: depth-ordered binning, forward and backward.
//
// This is the compiled fast path of reference_renderer (see _cpp.py for how it is built and
// called). It implements the per-pixel part of image formation; projection and SH colours are
// in project.cpp (and, as the readable reference, in PyTorch: projection.py, sh.py). The
// pure-PyTorch compositing in rasterize_torch.py implements the same rules and the tests
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
#include <type_traits>
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
    std::vector<int64_t> slot; // [count]: position in the tile's full list (its gradient slot)
    std::vector<float> bounds; // [count, 4]: x0, x1, y0, y1 of the alpha >= 1/255 ellipse, widened

    // Loads ids[0, n), the part of the tile's list that starts at position `first`.
    void load(const int32_t* ids, int64_t n, int64_t first, int64_t cam, int64_t N, int64_t D, const T* means2d,
              const T* conics, const T* opacities, const T* colors, const double box[4]) {
        channels = D;
        geo.resize(n * 7);
        color.resize(n * D);
        slot.resize(n);
        bounds.resize(n * 4);
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
            if (q[6] < T(0)) continue;  // sigma >= 0 wherever the conic is positive definite
            float* bb = &bounds[count * 4];
            if (!ellipse_bounds(q, bb)) {
                if (splat_misses_box(q, box[0], box[1], box[2], box[3])) continue;
            } else if (bb[1] < box[0] || bb[0] > box[1] || bb[3] < box[2] || bb[2] > box[3] ||
                       splat_misses_box(q, box[0], box[1], box[2], box[3])) {
                continue;
            }
            std::memcpy(&color[count * D], &colors[g * D], sizeof(T) * D);
            slot[count++] = first + k;
        }
    }

    // Axis-aligned box of {d : sigma(d) <= q[6]}: half-widths sqrt(2 q6 cov_xx) and
    // sqrt(2 q6 cov_yy) with cov the inverse conic; widened by 0.1 % and 0.01 px so rounding of
    // the per-pixel sigma cannot reach past it. False (no box) when the conic is not positive
    // definite, where sigma < 0 somewhere and the rules' skip decides.
    static bool ellipse_bounds(const T* q, float* bb) {
        const double a = q[2], b = q[3], c = q[4], det = a * c - b * b;
        if (!(a > 0 && c > 0 && det > 0 && std::isfinite(det))) {
            bb[0] = bb[2] = -std::numeric_limits<float>::infinity();
            bb[1] = bb[3] = std::numeric_limits<float>::infinity();
            return false;
        }
        const double hx = std::sqrt(2.0 * double(q[6]) * c / det) * 1.001 + 0.01;
        const double hy = std::sqrt(2.0 * double(q[6]) * a / det) * 1.001 + 0.01;
        bb[0] = float(double(q[0]) - hx);
        bb[1] = float(double(q[0]) + hx);
        bb[2] = float(double(q[1]) - hy);
        bb[3] = float(double(q[1]) + hy);
        return true;
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
    if (!(sigma >= T(0) && sigma <= q[6])) return false;  // written so that a NaN sigma is skipped too
    raw = q[5] * std::exp(-sigma);
    alpha = std::min(Consts<T>::alpha_max, raw);
    return alpha >= Consts<T>::alpha_min;
}

// A tile's list is consumed in batches of kBatch Gaussians, front to back, and a tile stops as
// soon as every one of its pixels has stopped (transmittance below 1e-4): behind an opaque
// surface, or in a small view where hundreds of splats cover each pixel, most of a tile's list
// is never loaded. Within a batch, each pixel block of kBlock x kBlock pixels gets the batch's
// Gaussians whose alpha >= 1/255 ellipse box reaches one of its pixel centres: small splats
// reach few pixels, so the per-pixel loops skip most of the batch. kBlock = 1 (a list per
// pixel) measured fastest: 6 % under 2 x 2 blocks and 13 % under 4 x 4 for 8 views of 128 px
// and 10k Gaussians, equal for 48 views of 16 px (benchmarks/bench_step.py's scene). Neither changes the image:
// a Gaussian left out has alpha < 1/255 at the pixel, and a stopped pixel takes nothing more.
// A block's list is a bit mask over the batch (kBatch / 64 words; 8 KiB for a 16 x 16 tile, so
// it stays in the L1 cache), walked in bit order, which is depth order: growing per-pixel
// vectors spent 15-20 % of the compositing in their capacity checks (perf, 2026-11-30).
constexpr int64_t kBlock = 1;
constexpr int64_t kBatch = 256;
constexpr int64_t kWords = kBatch / 64;
static_assert(kBatch % 64 == 0, "a batch's masks are whole 64-bit words");

// Calls fn(k) for every set bit k of a block's mask, in increasing order, until fn returns false.
template <typename Fn>
inline void for_each_bit(const uint64_t* mask, Fn&& fn) {
    for (int64_t w = 0; w < kWords; ++w) {
        for (uint64_t bits = mask[w]; bits != 0; bits &= bits - 1) {
            if (!fn(static_cast<int32_t>(w * 64 + __builtin_ctzll(bits)))) return;
        }
    }
}

// Pixel range of a tile and the lists of one batch per pixel block (indices into the batch).
template <typename T>
struct Blocks {
    int64_t bx = 0, by = 0, x_begin = 0, y_begin = 0, x_end = 0, y_end = 0;
    std::vector<uint64_t> masks;  // [blocks, kWords]: bit k set when batch Gaussian k may reach the block

    void set_tile(const Grid& grid, int64_t tx, int64_t ty) {
        x_begin = tx * grid.tile;
        y_begin = ty * grid.tile;
        x_end = std::min(grid.width, x_begin + grid.tile);
        y_end = std::min(grid.height, y_begin + grid.tile);
        bx = (x_end - x_begin + kBlock - 1) / kBlock;
        by = (y_end - y_begin + kBlock - 1) / kBlock;
        if (static_cast<int64_t>(masks.size()) < bx * by * kWords) masks.resize(bx * by * kWords);
    }
    int64_t width() const { return x_end - x_begin; }
    int64_t pixels() const { return (x_end - x_begin) * (y_end - y_begin); }
    // Tile's pixel box (centres) for the per-tile cull.
    void box(double out[4]) const { out[0] = x_begin + 0.5; out[1] = x_end - 0.5; out[2] = y_begin + 0.5; out[3] = y_end - 0.5; }

    void build(const TileSplats<T>& splats) {
        std::fill(masks.begin(), masks.begin() + bx * by * kWords, uint64_t(0));
        auto range = [](float lo, float hi, int64_t begin, int64_t n, int64_t& r0, int64_t& r1) {
            // blocks holding a pixel x with lo <= x + 0.5 <= hi (the box is already widened)
            const double first = std::ceil(double(lo) - 0.5) - double(begin);
            const double last = std::floor(double(hi) - 0.5) - double(begin);
            r0 = first <= 0 ? 0 : std::min<int64_t>(n, static_cast<int64_t>(first) / kBlock);
            r1 = last < 0 ? 0 : std::min<int64_t>(n, static_cast<int64_t>(std::min(last, 1e9)) / kBlock + 1);
        };
        for (int64_t k = 0; k < splats.count; ++k) {
            const float* bb = &splats.bounds[k * 4];
            int64_t x0, x1, y0, y1;
            range(bb[0], bb[1], x_begin, bx, x0, x1);
            range(bb[2], bb[3], y_begin, by, y0, y1);
            const uint64_t bit = uint64_t(1) << (k & 63);
            uint64_t* word = masks.data() + (k >> 6);
            for (int64_t j = y0; j < y1; ++j)
                for (int64_t i = x0; i < x1; ++i) word[(j * bx + i) * kWords] |= bit;
        }
    }

    // fn(x, y, p, mask) for every pixel of the tile (p: its index in the tile), block by block.
    template <typename Fn>
    void for_pixels(Fn&& fn) const {
        for (int64_t j = 0; j < by; ++j) {
            for (int64_t i = 0; i < bx; ++i) {
                const uint64_t* mask = masks.data() + (j * bx + i) * kWords;
                const int64_t x0 = x_begin + i * kBlock, y0 = y_begin + j * kBlock;
                for (int64_t y = y0; y < std::min(y_end, y0 + kBlock); ++y)
                    for (int64_t x = x0; x < std::min(x_end, x0 + kBlock); ++x)
                        fn(x, y, (y - y_begin) * width() + (x - x_begin), mask);
            }
        }
    }
};

// Per-thread scratch of the compositing passes, reused from tile to tile. Reached through a
// local reference: a thread_local named inside the per-pixel loops costs a TLS lookup per use
// in a shared library (2-3 % of a training step, perf, 2026-11-30).
template <typename T>
struct Scratch {
    Blocks<T> blocks;
    TileSplats<T> splats;
    std::vector<T> acc, trans;
    std::vector<int32_t> last;
    std::vector<uint8_t> done;
};

template <typename T>
Scratch<T>& thread_scratch() {
    thread_local Scratch<T> scratch;
    return scratch;
}

// Only float (the training path) unrolls its colour channels: in double, the tests' reference
// precision, the arithmetic stays the generic loop's, rounding and all.
template <typename T>
constexpr bool kUnroll = std::is_same<T, float>::value;

// Blend statistics per intersection (forward, when asked): summed weight, pixel count.
constexpr int64_t kBlendSlots = 2;

// kD > 0: the colour channels as a compile-time constant (the channel loops unroll); 0: D.
template <typename T, int kD>
void forward(const Grid& grid, int64_t C, int64_t N, int64_t D_, const T* means2d, const T* conics,
             const T* opacities, const T* colors, const T* backgrounds, const int64_t* offsets,
             const int32_t* ids, T* out_color, T* out_trans, int32_t* out_last, T* isect_blend, int n_threads) {
    const int64_t D = kD > 0 ? kD : D_;
    const int64_t n_tiles = grid.n_tiles();
    parallel_for(C * n_tiles, n_threads, [&](int64_t item, int) {
        const int64_t cam = item / n_tiles, t = item % n_tiles;
        const int64_t begin = offsets[item], end = offsets[item + 1];
        // What each (tile, Gaussian) pair blended: its weight alpha * T summed over the tile's
        // pixels, then how many pixels (the tile's own slots, as the backward's gradients).
        T* blend = isect_blend ? isect_blend + begin * kBlendSlots : nullptr;
        if (blend) std::fill(blend, blend + (end - begin) * kBlendSlots, T(0));
        Scratch<T>& s = thread_scratch<T>();
        Blocks<T>& blocks = s.blocks;
        TileSplats<T>& splats = s.splats;
        std::vector<T>& acc = s.acc;
        std::vector<T>& trans = s.trans;
        std::vector<int32_t>& last = s.last;
        std::vector<uint8_t>& done = s.done;
        blocks.set_tile(grid, t % grid.tiles_x, t / grid.tiles_x);
        const int64_t n_pix = blocks.pixels();
        acc.assign(n_pix * D, T(0));
        trans.assign(n_pix, T(1));
        last.assign(n_pix, 0);
        done.assign(n_pix, 0);
        double box[4];
        blocks.box(box);
        int64_t running = n_pix;
        for (int64_t b0 = 0; b0 < end - begin && running > 0; b0 += kBatch) {
            splats.load(ids + begin + b0, std::min(kBatch, end - begin - b0), b0, cam, N, D, means2d, conics,
                        opacities, colors, box);
            if (splats.count == 0) continue;
            blocks.build(splats);
            const T* geo = splats.geo.data();
            const T* col = splats.color.data();
            const int64_t* slot = splats.slot.data();
            blocks.for_pixels([&](int64_t x, int64_t y, int64_t p, const uint64_t* mask) {
                if (done[p]) return;
                const T px = T(x) + T(0.5), py = T(y) + T(0.5);
                T* a = &acc[p * D];
                T tr = trans[p];
                int32_t lst = last[p];
                for_each_bit(mask, [&](int32_t k) {
                    T alpha, raw, dx, dy;
                    if (!splat_alpha(geo + k * 7, px, py, alpha, raw, dx, dy)) return true;
                    const T next = tr * (T(1) - alpha);
                    if (next < Consts<T>::t_min) {
                        done[p] = 1;
                        --running;
                        return false;
                    }
                    const T w = alpha * tr;
                    const T* c = col + k * D;
                    for (int64_t ch = 0; ch < D; ++ch) a[ch] += w * c[ch];
                    if (blend) {
                        blend[slot[k] * kBlendSlots] += w;
                        blend[slot[k] * kBlendSlots + 1] += T(1);
                    }
                    tr = next;
                    lst = static_cast<int32_t>(slot[k] + 1);
                    return true;
                });
                trans[p] = tr;
                last[p] = lst;
            });
        }
        const T* bg = backgrounds + cam * D;
        blocks.for_pixels([&](int64_t x, int64_t y, int64_t p, const uint64_t*) {
            const int64_t pix = (cam * grid.height + y) * grid.width + x;
            for (int64_t ch = 0; ch < D; ++ch) out_color[pix * D + ch] = acc[p * D + ch] + trans[p] * bg[ch];
            out_trans[pix] = trans[p];
            out_last[pix] = last[p];  // 1 + the position in the tile's list of its last contributor
        });
    });
}

// Gradient slots per intersection (tile, Gaussian): d/du, d/dv, d/da, d/db, d/dc, d/do,
// |d/du|, |d/dv| summed over the tile's pixels, then d/dcolor. Each tile owns its slots, so
// threads never write to the same memory and the result does not depend on scheduling.
constexpr int64_t kGeoSlots = 8;

// The backward walks each pixel's contributors front to back, in the forward's order, with the
// exact transmittances (no division by 1 - alpha to walk back from the final one). What a
// contributor hides behind it (later colours and the background) is the pixel's colour minus
// what it and those before it added: out_color - sum_{j <= k} c_j w_j.
template <typename T, int kD>
void backward(const Grid& grid, int64_t C, int64_t N, int64_t D_, const T* means2d, const T* conics,
              const T* opacities, const T* colors, const T* backgrounds, const int64_t* offsets,
              const int32_t* ids, const T* out_color, const T* out_trans, const int32_t* out_last,
              const T* grad_color, const T* grad_alpha, T* isect_grads, int n_threads) {
    const int64_t D = kD > 0 ? kD : D_;
    const int64_t n_tiles = grid.n_tiles();
    const int64_t slots = kGeoSlots + D;
    parallel_for(C * n_tiles, n_threads, [&](int64_t item, int) {
        const int64_t cam = item / n_tiles, t = item % n_tiles;
        const int64_t begin = offsets[item], end = offsets[item + 1];
        if (end == begin) return;
        T* g_tile = isect_grads + begin * slots;
        std::fill(g_tile, g_tile + (end - begin) * slots, T(0));
        Scratch<T>& s = thread_scratch<T>();
        Blocks<T>& blocks = s.blocks;
        TileSplats<T>& splats = s.splats;
        std::vector<T>& trans = s.trans;
        std::vector<T>& added = s.acc;
        blocks.set_tile(grid, t % grid.tiles_x, t / grid.tiles_x);
        const int64_t n_pix = blocks.pixels();
        trans.assign(n_pix, T(1));
        added.assign(n_pix * D, T(0));
        int64_t max_last = 0;
        blocks.for_pixels([&](int64_t x, int64_t y, int64_t, const uint64_t*) {
            max_last = std::max<int64_t>(max_last, out_last[(cam * grid.height + y) * grid.width + x]);
        });
        double box[4];
        blocks.box(box);
        for (int64_t b0 = 0; b0 < max_last; b0 += kBatch) {
            splats.load(ids + begin + b0, std::min(kBatch, end - begin - b0), b0, cam, N, D, means2d, conics,
                        opacities, colors, box);
            if (splats.count == 0) continue;
            blocks.build(splats);
            const T* geo = splats.geo.data();
            const T* col = splats.color.data();
            const int64_t* slot = splats.slot.data();
            blocks.for_pixels([&](int64_t x, int64_t y, int64_t p, const uint64_t* mask) {
                const int64_t pix = (cam * grid.height + y) * grid.width + x;
                const int32_t last = out_last[pix];
                if (last <= b0) return;
                const T px = T(x) + T(0.5), py = T(y) + T(0.5);
                const T final_trans = out_trans[pix], ga = grad_alpha[pix];
                const T* gc = grad_color + pix * D;
                const T* color = out_color + pix * D;
                T* sum = &added[p * D];
                T tr = trans[p];
                for_each_bit(mask, [&](int32_t k) {
                    if (slot[k] >= last) return false;
                    T alpha, raw, dx, dy;
                    const T* q = geo + k * 7;
                    if (!splat_alpha(q, px, py, alpha, raw, dx, dy)) return true;
                    const T* c = col + k * D;
                    T* g = g_tile + slot[k] * slots;
                    const T w = alpha * tr;
                    const T inv_keep = T(1) / (T(1) - alpha);
                    // dL/dalpha: own colour seen through T, minus what it hides behind it (scaled
                    // by 1 / (1 - alpha)); the rendered alpha 1 - T_final grows by T_final / (1 - alpha).
                    T g_alpha = ga * final_trans * inv_keep;
                    for (int64_t ch = 0; ch < D; ++ch) {
                        sum[ch] += c[ch] * w;
                        g[kGeoSlots + ch] += gc[ch] * w;
                        g_alpha += gc[ch] * (c[ch] * tr - (color[ch] - sum[ch]) * inv_keep);
                    }
                    tr *= T(1) - alpha;
                    if (raw > Consts<T>::alpha_max) return true;  // alpha = 0.999 does not depend on o or sigma
                    const T g_sigma = -g_alpha * alpha;
                    const T gu = g_sigma * (q[2] * dx + q[3] * dy);
                    const T gv = g_sigma * (q[3] * dx + q[4] * dy);
                    g[0] += gu;
                    g[1] += gv;
                    g[2] += g_sigma * T(0.5) * dx * dx;
                    g[3] += g_sigma * dx * dy;
                    g[4] += g_sigma * T(0.5) * dy * dy;
                    g[5] += g_alpha * alpha / q[5];
                    g[6] += std::abs(gu);
                    g[7] += std::abs(gv);
                    return true;
                });
                trans[p] = tr;
            });
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

// Sums the per-intersection blend statistics into per-(camera, Gaussian) weight and pixel
// counts, in the same fixed order as reduce().
template <typename T>
void reduce_blend(const Grid& grid, int64_t C, int64_t N, const int64_t* offsets, const int32_t* ids,
                  const T* isect_blend, T* blend_weight, T* blend_pixels, int n_threads) {
    const int64_t n_tiles = grid.n_tiles();
    parallel_for(C, n_threads, [&](int64_t cam, int) {
        for (int64_t i = offsets[cam * n_tiles]; i < offsets[(cam + 1) * n_tiles]; ++i) {
            const int64_t g = cam * N + ids[i];
            blend_weight[g] += isect_blend[i * kBlendSlots];
            blend_pixels[g] += isect_blend[i * kBlendSlots + 1];
        }
    });
}

}  // namespace

namespace {

// Valid Gaussians of one camera in depth order, ties by index (what a stable argsort of the
// depths gives). Depths of valid Gaussians are > near > 0, and positive IEEE floats order as
// their bit patterns, so an LSD radix sort on the bits (11-bit digits; stable, and the input is
// in index order) does it in a few linear passes instead of a comparison sort.
template <typename T>
void depth_order(int64_t N, const T* depths, const uint8_t* valid, std::vector<int32_t>& order,
                 std::vector<int32_t>& tmp) {
    using Key = typename std::conditional<sizeof(T) == 4, uint32_t, uint64_t>::type;
    order.clear();
    for (int64_t n = 0; n < N; ++n)
        if (valid[n]) order.push_back(static_cast<int32_t>(n));
    tmp.resize(order.size());
    auto key = [&](int32_t n) { Key k; std::memcpy(&k, &depths[n], sizeof(T)); return k; };
    constexpr int kBits = 11;
    constexpr int kPasses = (8 * sizeof(Key) + kBits - 1) / kBits;
    std::vector<int64_t> count(size_t(1) << kBits);
    for (int pass = 0; pass < kPasses; ++pass) {
        const int shift = pass * kBits;
        std::fill(count.begin(), count.end(), 0);
        bool same = true;
        const Key first = order.empty() ? 0 : (key(order[0]) >> shift) & ((Key(1) << kBits) - 1);
        for (int32_t n : order) {
            const Key d = (key(n) >> shift) & ((Key(1) << kBits) - 1);
            same = same && d == first;
            ++count[d];
        }
        if (same) continue;  // this digit is equal everywhere: the pass would not move anything
        int64_t sum = 0;
        for (auto& c : count) { const int64_t c0 = c; c = sum; sum += c0; }
        for (int32_t n : order) tmp[count[(key(n) >> shift) & ((Key(1) << kBits) - 1)]++] = n;
        order.swap(tmp);
    }
}

template <typename T>
int64_t bin_count(int64_t C, int64_t N, int64_t tiles_x, int64_t tiles_y, const int32_t* rects,
                  const uint8_t* valid, int64_t* offsets, int n_threads) {
    const int64_t n_tiles = tiles_x * tiles_y;
    std::fill(offsets, offsets + C * n_tiles + 1, int64_t(0));
    parallel_for(C, n_threads, [&](int64_t cam, int) {
        int64_t* cnt = offsets + cam * n_tiles + 1;
        for (int64_t n = 0; n < N; ++n) {
            if (!valid[cam * N + n]) continue;
            const int32_t* r = rects + (cam * N + n) * 4;
            for (int64_t ty = r[2]; ty < r[3]; ++ty)
                for (int64_t tx = r[0]; tx < r[1]; ++tx) ++cnt[ty * tiles_x + tx];
        }
    });
    for (int64_t i = 0; i < C * n_tiles; ++i) offsets[i + 1] += offsets[i];
    return offsets[C * n_tiles];
}

template <typename T>
void bin_fill(int64_t C, int64_t N, int64_t tiles_x, int64_t tiles_y, const int32_t* rects,
              const T* depths, const uint8_t* valid, const int64_t* offsets, int32_t* ids, int n_threads) {
    const int64_t n_tiles = tiles_x * tiles_y;
    parallel_for(C, n_threads, [&](int64_t cam, int) {
        thread_local std::vector<int32_t> order, tmp;
        depth_order(N, depths + cam * N, valid + cam * N, order, tmp);
        std::vector<int64_t> cursor(offsets + cam * n_tiles, offsets + (cam + 1) * n_tiles);
        for (int32_t n : order) {
            const int32_t* r = rects + (cam * N + n) * 4;
            for (int64_t ty = r[2]; ty < r[3]; ++ty)
                for (int64_t tx = r[0]; tx < r[1]; ++tx) ids[cursor[ty * tiles_x + tx]++] = n;
        }
    });
}

}  // namespace

extern "C" {

// Tile lists in depth order straight from the projection: counts (returns the total; offsets
// [C * tiles + 1] get the prefix sums), then fills ids. Cameras run in parallel.
#define MVGS_BIN(T, SUFFIX)                                                                        \
    int64_t mvgs_bin_depth_count_##SUFFIX(int64_t C, int64_t N, int64_t tiles_x, int64_t tiles_y,  \
                                          const int32_t* rects, const uint8_t* valid,             \
                                          int64_t* offsets, int n_threads) {                      \
        return bin_count<T>(C, N, tiles_x, tiles_y, rects, valid, offsets, n_threads);            \
    }                                                                                              \
    void mvgs_bin_depth_fill_##SUFFIX(int64_t C, int64_t N, int64_t tiles_x, int64_t tiles_y,      \
                                      const int32_t* rects, const T* depths, const uint8_t* valid,  \
                                      const int64_t* offsets, int32_t* ids, int n_threads) {        \
        bin_fill<T>(C, N, tiles_x, tiles_y, rects, depths, valid, offsets, ids, n_threads);        \
    }

MVGS_BIN(float, f32)
MVGS_BIN(double, f64)

#undef MVGS_BIN

#define MVGS_DEFINE(T, SUFFIX)                                                                    \
    void mvgs_forward_##SUFFIX(int64_t C, int64_t N, int64_t D, int64_t width, int64_t height,     \
                               int64_t tile, const T* means2d, const T* conics, const T* opacities, \
                               const T* colors, const T* backgrounds, const int64_t* offsets,      \
                               const int32_t* ids, T* out_color, T* out_trans, int32_t* out_last,  \
                               T* isect_blend, T* blend_weight, T* blend_pixels, int n_threads) {  \
        const Grid grid{width, height, tile, (width + tile - 1) / tile, (height + tile - 1) / tile}; \
        auto run = D == 3 && kUnroll<T> ? &forward<T, 3> : &forward<T, 0>;                                       \
        run(grid, C, N, D, means2d, conics, opacities, colors, backgrounds, offsets, ids,           \
            out_color, out_trans, out_last, isect_blend, n_threads);                               \
        if (isect_blend)                                                                           \
            reduce_blend<T>(grid, C, N, offsets, ids, isect_blend, blend_weight, blend_pixels,      \
                            n_threads);                                                            \
    }                                                                                              \
    void mvgs_backward_##SUFFIX(int64_t C, int64_t N, int64_t D, int64_t width, int64_t height,    \
                                int64_t tile, const T* means2d, const T* conics,                    \
                                const T* opacities, const T* colors, const T* backgrounds,          \
                                const int64_t* offsets, const int32_t* ids, const T* out_color,     \
                                const T* out_trans, const int32_t* out_last, const T* grad_color,   \
                                const T* grad_alpha,                                                \
                                T* isect_grads, T* grad_means2d, T* grad_conics,                    \
                                T* grad_opacities, T* grad_colors, T* absgrad_means2d,              \
                                int n_threads) {                                                   \
        const Grid grid{width, height, tile, (width + tile - 1) / tile, (height + tile - 1) / tile}; \
        auto run = D == 3 && kUnroll<T> ? &backward<T, 3> : &backward<T, 0>;                                     \
        run(grid, C, N, D, means2d, conics, opacities, colors, backgrounds, offsets, ids,           \
            out_color, out_trans, out_last, grad_color, grad_alpha, isect_grads, n_threads);       \
        reduce<T>(grid, C, N, D, offsets, ids, isect_grads, grad_means2d, grad_conics,              \
                  grad_opacities, grad_colors, absgrad_means2d, n_threads);                        \
    }

MVGS_DEFINE(float, f32)
MVGS_DEFINE(double, f64)

#undef MVGS_DEFINE

}  // extern "C"
