// Fused EWA projection and SH colours for C cameras at once, with a hand-written backward.
//
// The compiled twin of projection.py + sh.py (the PyTorch path stays the readable reference and
// the tests compare the two). Written by hand because through autograd the same maths costs
// about 100 small tensor operations per call and as many in backward, each over [C, N]: for the
// pyramid's many small views that fixed cost, not the pixels, was most of a training step.
//
// Layout of the work: per-Gaussian quantities that do not depend on the view (rotation, 3D
// covariance) are formed once per call; the per-(camera, Gaussian) pass runs over blocks of
// Gaussians, each block looping over all cameras, so the backward accumulates a Gaussian's
// gradient over cameras in one thread (no atomics, deterministic order).
//
// Every formula below is the one in projection.py, including its guards for culled Gaussians
// (a harmless depth of 1, a determinant of 1 where the splat is degenerate), so the gradients
// equal autograd's on the PyTorch path for any upstream gradient, up to rounding (the forward
// multiplies by one reciprocal of the depth and of the determinant where PyTorch divides).

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <thread>
#include <type_traits>
#include <vector>

namespace {

template <typename Fn>
void parallel_blocks(int64_t n, int64_t block, int n_threads, Fn&& fn) {
    const int64_t n_blocks = (n + block - 1) / block;
    n_threads = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(n_threads, n_blocks)));
    std::atomic<int64_t> next(0);
    auto worker = [&]() {
        for (int64_t b = next.fetch_add(1); b < n_blocks; b = next.fetch_add(1))
            fn(b * block, std::min(n, (b + 1) * block));
    };
    if (n_threads == 1) {
        worker();
        return;
    }
    std::vector<std::thread> pool;
    for (int t = 1; t < n_threads; ++t) pool.emplace_back(worker);
    worker();
    for (auto& th : pool) th.join();
}

constexpr double kC0 = 0.28209479177387814;
constexpr double kC1 = 0.4886025119029199;
constexpr double kC2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                           -1.0925484305920792, 0.5462742152960396};
constexpr double kC3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                           0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                           -0.5900435899266435};

// Real SH basis (3DGS convention) at a unit direction; n = (degree + 1)^2 values.
template <typename T>
inline void sh_basis(int degree, T x, T y, T z, T* b) {
    b[0] = T(kC0);
    if (degree < 1) return;
    b[1] = -T(kC1) * y;
    b[2] = T(kC1) * z;
    b[3] = -T(kC1) * x;
    if (degree < 2) return;
    const T xx = x * x, yy = y * y, zz = z * z;
    b[4] = T(kC2[0]) * x * y;
    b[5] = T(kC2[1]) * y * z;
    b[6] = T(kC2[2]) * (T(2) * zz - xx - yy);
    b[7] = T(kC2[3]) * x * z;
    b[8] = T(kC2[4]) * (xx - yy);
    if (degree < 3) return;
    b[9] = T(kC3[0]) * y * (T(3) * xx - yy);
    b[10] = T(kC3[1]) * x * y * z;
    b[11] = T(kC3[2]) * y * (T(4) * zz - xx - yy);
    b[12] = T(kC3[3]) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
    b[13] = T(kC3[4]) * x * (T(4) * zz - xx - yy);
    b[14] = T(kC3[5]) * z * (xx - yy);
    b[15] = T(kC3[6]) * x * (xx - T(3) * yy);
}

// Colour max(SH value + 0.5, 0) per channel at unit direction dir; coef [K, 3].
template <typename T, int DEG>
inline void sh_color(const T* dir, const T* coef, T* out) {
    constexpr int n = (DEG + 1) * (DEG + 1);
    T basis[16];
    sh_basis(DEG, dir[0], dir[1], dir[2], basis);
    T acc[3] = {T(0), T(0), T(0)};
    for (int k = 0; k < n; ++k)
        for (int ch = 0; ch < 3; ++ch) acc[ch] += basis[k] * coef[k * 3 + ch];
    for (int ch = 0; ch < 3; ++ch) out[ch] = std::max(acc[ch] + T(0.5), T(0));
}

// d/d(x, y, z) of sum_k gb[k] * basis_k(x, y, z) (the basis as a polynomial in 3D).
template <typename T>
inline void sh_basis_vjp(int degree, T x, T y, T z, const T* gb, T& gx, T& gy, T& gz) {
    gx = gy = gz = T(0);
    if (degree < 1) return;
    gy -= T(kC1) * gb[1];
    gz += T(kC1) * gb[2];
    gx -= T(kC1) * gb[3];
    if (degree < 2) return;
    const T xx = x * x, yy = y * y, zz = z * z;
    gx += T(kC2[0]) * y * gb[4];
    gy += T(kC2[0]) * x * gb[4];
    gy += T(kC2[1]) * z * gb[5];
    gz += T(kC2[1]) * y * gb[5];
    gx += T(-2 * kC2[2]) * x * gb[6];
    gy += T(-2 * kC2[2]) * y * gb[6];
    gz += T(4 * kC2[2]) * z * gb[6];
    gx += T(kC2[3]) * z * gb[7];
    gz += T(kC2[3]) * x * gb[7];
    gx += T(2 * kC2[4]) * x * gb[8];
    gy += T(-2 * kC2[4]) * y * gb[8];
    if (degree < 3) return;
    gx += T(kC3[0]) * T(6) * x * y * gb[9];
    gy += T(kC3[0]) * (T(3) * xx - T(3) * yy) * gb[9];
    gx += T(kC3[1]) * y * z * gb[10];
    gy += T(kC3[1]) * x * z * gb[10];
    gz += T(kC3[1]) * x * y * gb[10];
    gx += T(kC3[2]) * T(-2) * x * y * gb[11];
    gy += T(kC3[2]) * (T(4) * zz - xx - T(3) * yy) * gb[11];
    gz += T(kC3[2]) * T(8) * y * z * gb[11];
    gx += T(kC3[3]) * T(-6) * x * z * gb[12];
    gy += T(kC3[3]) * T(-6) * y * z * gb[12];
    gz += T(kC3[3]) * (T(6) * zz - T(3) * xx - T(3) * yy) * gb[12];
    gx += T(kC3[4]) * (T(4) * zz - T(3) * xx - yy) * gb[13];
    gy += T(kC3[4]) * T(-2) * x * y * gb[13];
    gz += T(kC3[4]) * T(8) * x * z * gb[13];
    gx += T(kC3[5]) * T(2) * x * z * gb[14];
    gy += T(kC3[5]) * T(-2) * y * z * gb[14];
    gz += T(kC3[5]) * (xx - yy) * gb[14];
    gx += T(kC3[6]) * (T(3) * xx - T(3) * yy) * gb[15];
    gy += T(kC3[6]) * T(-6) * x * y * gb[15];
}

// Rotation matrix (row-major) of the normalised quaternion w-x-y-z; qn gets the unit quaternion.
template <typename T>
inline void quat_rotation(const T* q, T* qn, T& norm, T* R) {
    norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const T inv = T(1) / std::max(norm, T(1e-12));
    for (int i = 0; i < 4; ++i) qn[i] = q[i] * inv;
    const T w = qn[0], x = qn[1], y = qn[2], z = qn[3];
    R[0] = T(1) - T(2) * (y * y + z * z); R[1] = T(2) * (x * y - w * z); R[2] = T(2) * (x * z + w * y);
    R[3] = T(2) * (x * y + w * z); R[4] = T(1) - T(2) * (x * x + z * z); R[5] = T(2) * (y * z - w * x);
    R[6] = T(2) * (x * z - w * y); R[7] = T(2) * (y * z + w * x); R[8] = T(1) - T(2) * (x * x + y * y);
}

// Symmetric 3x3 stored as xx, xy, xz, yy, yz, zz.
template <typename T>
inline void sym_mul(const T* S, const T* v, T* out) {
    out[0] = S[0] * v[0] + S[1] * v[1] + S[2] * v[2];
    out[1] = S[1] * v[0] + S[3] * v[1] + S[4] * v[2];
    out[2] = S[2] * v[0] + S[4] * v[1] + S[5] * v[2];
}

template <typename T>
struct Cam {
    T R[9], t[3], fx, fy, cx, cy, lo_x, hi_x, lo_y, hi_y, center[3], t_abs;

    template <typename U>
    void load(const U* viewmat, const U* K, int64_t width, int64_t height) {
        for (int i = 0; i < 3; ++i) {
            for (int j = 0; j < 3; ++j) R[i * 3 + j] = T(viewmat[i * 4 + j]);
            t[i] = T(viewmat[i * 4 + 3]);
        }
        fx = T(K[0]); fy = T(K[4]); cx = T(K[2]); cy = T(K[5]);
        t_abs = std::abs(t[0]) + std::abs(t[1]) + std::abs(t[2]);
        const T tan_x = T(0.5) * T(width) / fx, tan_y = T(0.5) * T(height) / fy;
        lo_x = -(cx / fx + T(0.3) * tan_x); hi_x = (T(width) - cx) / fx + T(0.3) * tan_x;
        lo_y = -(cy / fy + T(0.3) * tan_y); hi_y = (T(height) - cy) / fy + T(0.3) * tan_y;
        for (int j = 0; j < 3; ++j)  // -R^T t
            center[j] = -(R[0 * 3 + j] * t[0] + R[1 * 3 + j] * t[1] + R[2 * 3 + j] * t[2]);
    }
};

struct Settings {
    int64_t C, N, width, height, tile, K, sh_degree;  // sh_degree < 0: no colours
    double near_plane, far_plane, eps2d, radius_clip;
};

// The cameras in precision G (the model's T for colours, double for the geometry).
template <typename G, typename T>
std::vector<Cam<G>> load_cameras(const Settings& s, const T* viewmats, const T* Ks) {
    std::vector<Cam<G>> cams(s.C);
    for (int64_t c = 0; c < s.C; ++c) cams[c].load(viewmats + c * 16, Ks + c * 9, s.width, s.height);
    return cams;
}

// Intermediate values of one (camera, Gaussian) pair, shared by forward and backward.
// Determinant floors below which a pair is culled: its conic 1/det and the backward's 1/det^2
// would overflow. float's floor also sends a float pair to be done again in double (needs_double);
// double's is projection.py's DET_FLOOR.
constexpr double kFloatDetFloor = 1e-18;
constexpr double kDoubleDetFloor = 1e-150;

template <typename T>
struct Pair {
    T p[3], zs, inv_zs, xz, yz, raw_xz, raw_yz, jw0[3], jw1[3], s0[3], s1[3], a_raw, b, c_raw, a, c, det, det_s;
    bool in_depth, ok;

    void compute(const Cam<T>& cam, const T* mean, const T* cov, const Settings& s) {
        for (int i = 0; i < 3; ++i)
            p[i] = cam.R[i * 3] * mean[0] + cam.R[i * 3 + 1] * mean[1] + cam.R[i * 3 + 2] * mean[2] + cam.t[i];
        in_depth = p[2] > T(s.near_plane) && p[2] < T(s.far_plane);
        zs = in_depth ? p[2] : T(1);
        inv_zs = T(1) / zs;  // one division, then products (a few ulp from projection.py's quotients)
        raw_xz = p[0] * inv_zs;
        raw_yz = p[1] * inv_zs;
        xz = std::min(std::max(raw_xz, cam.lo_x), cam.hi_x);
        yz = std::min(std::max(raw_yz, cam.lo_y), cam.hi_y);
        const T A0 = cam.fx * inv_zs, B0 = cam.fx * xz * inv_zs, A1 = cam.fy * inv_zs, B1 = cam.fy * yz * inv_zs;
        for (int j = 0; j < 3; ++j) {
            jw0[j] = A0 * cam.R[j] - B0 * cam.R[6 + j];
            jw1[j] = A1 * cam.R[3 + j] - B1 * cam.R[6 + j];
        }
        sym_mul(cov, jw0, s0);
        sym_mul(cov, jw1, s1);
        a_raw = jw0[0] * s0[0] + jw0[1] * s0[1] + jw0[2] * s0[2];
        b = jw0[0] * s1[0] + jw0[1] * s1[1] + jw0[2] * s1[2];
        c_raw = jw1[0] * s1[0] + jw1[1] * s1[1] + jw1[2] * s1[2];
        a = a_raw + T(s.eps2d);
        c = c_raw + T(s.eps2d);
        det = a * c - b * b;
        // Below the floor the conic 1/det and its backward's 1/det^2 would overflow: such a splat
        // (a standard deviation under 1e-37 px in double) is culled; a float pair at its floor is
        // done again in double (see needs_double).
        const T det_floor = T(std::is_same<T, float>::value ? kFloatDetFloor : kDoubleDetFloor);
        ok = in_depth && det > det_floor && std::isfinite(det);
        det_s = ok ? det : T(1);
    }
};

// Per Gaussian: unit quaternion, its norm, R and the covariance R S S^T R^T (6 entries).
template <typename T>
inline void gaussian_cov(const T* quat, const T* scale, T* qn, T& qnorm, T* R, T* cov) {
    quat_rotation(quat, qn, qnorm, R);
    T M[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) M[i * 3 + j] = R[i * 3 + j] * scale[j];
    const int idx[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
    for (int e = 0; e < 6; ++e) {
        const T* r0 = &M[idx[e][0] * 3];
        const T* r1 = &M[idx[e][1] * 3];
        cov[e] = r0[0] * r1[0] + r0[1] * r1[1] + r0[2] * r1[2];
    }
}

// Per-Gaussian quantities of a block of Gaussians, formed once per call and shared by all cameras.
constexpr int64_t kGaussians = 64;

template <typename T>
struct GaussianBlock {
    T qn[kGaussians][4], qnorm[kGaussians], R[kGaussians][9], cov[kGaussians][6], smax2[kGaussians],
        smin2[kGaussians];

    void load(int64_t n0, int64_t n1, const T* quats, const T* scales) {
        for (int64_t n = n0; n < n1; ++n) {
            const int64_t i = n - n0;
            const T* sc = scales + n * 3;
            gaussian_cov(quats + n * 4, sc, qn[i], qnorm[i], R[i], cov[i]);
            smax2[i] = std::max(sc[0] * sc[0], std::max(sc[1] * sc[1], sc[2] * sc[2]));
            smin2[i] = std::min(sc[0] * sc[0], std::min(sc[1] * sc[1], sc[2] * sc[2]));
        }
    }
};


// Colour of one pair through SH, backward: adds to the coefficient gradients and to the mean's
// (through the view direction). Channels clamped at 0 pass no gradient (torch.clamp_min's rule).
template <typename T>
inline void sh_backward(int degree, int n_basis, const Cam<T>& cam, const T* mean, const T* coef,
                        const T* gc, T* dsh, T* dm) {
    T d[3];
    for (int j = 0; j < 3; ++j) d[j] = mean[j] - cam.center[j];
    const T len = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    const T inv = T(1) / std::max(len, T(1e-12));
    const T dir[3] = {d[0] * inv, d[1] * inv, d[2] * inv};
    T basis[16], gb[16];
    sh_basis(degree, dir[0], dir[1], dir[2], basis);
    T g[3];
    for (int ch = 0; ch < 3; ++ch) {
        T acc = T(0);
        for (int k = 0; k < n_basis; ++k) acc += basis[k] * coef[k * 3 + ch];
        g[ch] = acc + T(0.5) >= T(0) ? gc[ch] : T(0);
    }
    for (int k = 0; k < n_basis; ++k) {
        gb[k] = coef[k * 3] * g[0] + coef[k * 3 + 1] * g[1] + coef[k * 3 + 2] * g[2];
        for (int ch = 0; ch < 3; ++ch) dsh[k * 3 + ch] += basis[k] * g[ch];
    }
    T gdir[3];
    sh_basis_vjp(degree, dir[0], dir[1], dir[2], gb, gdir[0], gdir[1], gdir[2]);
    if (len > T(1e-12)) {
        const T dot = dir[0] * gdir[0] + dir[1] * gdir[1] + dir[2] * gdir[2];
        for (int j = 0; j < 3; ++j) dm[j] += (gdir[j] - dir[j] * dot) / len;
    } else {
        for (int j = 0; j < 3; ++j) dm[j] += gdir[j] / T(1e-12);
    }
}

// Covariance R S S^T R^T, backward: from the gradient w.r.t. its 6 distinct entries to the
// quaternion (through the normalisation) and the scales.
template <typename T>
inline void cov_backward(const T* qn, T qnorm, const T* R, const T* scale, const T* dcov, T* dq, T* ds) {
    T M[9], dM[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) M[i * 3 + j] = R[i * 3 + j] * scale[j];
    const int idx[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
    for (int e = 0; e < 6; ++e) {
        const int i = idx[e][0], j = idx[e][1];
        for (int k = 0; k < 3; ++k) {
            dM[i * 3 + k] += dcov[e] * M[j * 3 + k];
            dM[j * 3 + k] += dcov[e] * M[i * 3 + k];
        }
    }
    T dR[9];
    for (int j = 0; j < 3; ++j) {
        ds[j] = dM[j] * R[j] + dM[3 + j] * R[3 + j] + dM[6 + j] * R[6 + j];
        for (int i = 0; i < 3; ++i) dR[i * 3 + j] = dM[i * 3 + j] * scale[j];
    }
    const T w = qn[0], x = qn[1], y = qn[2], z = qn[3];
    T g[4];
    g[0] = T(2) * (-z * dR[1] + y * dR[2] + z * dR[3] - x * dR[5] - y * dR[6] + x * dR[7]);
    g[1] = T(2) * (y * dR[1] + z * dR[2] + y * dR[3] - T(2) * x * dR[4] - w * dR[5] + z * dR[6] +
                   w * dR[7] - T(2) * x * dR[8]);
    g[2] = T(2) * (-T(2) * y * dR[0] + x * dR[1] + w * dR[2] + x * dR[3] + z * dR[5] - w * dR[6] +
                   z * dR[7] - T(2) * y * dR[8]);
    g[3] = T(2) * (-T(2) * z * dR[0] - w * dR[1] + x * dR[2] + w * dR[3] - T(2) * z * dR[4] +
                   y * dR[5] + x * dR[6] + y * dR[7]);
    if (qnorm > T(1e-12)) {
        const T dot = w * g[0] + x * g[1] + y * g[2] + z * g[3];
        for (int i = 0; i < 4; ++i) dq[i] = (g[i] - qn[i] * dot) / qnorm;
    } else {
        for (int i = 0; i < 4; ++i) dq[i] = g[i] / T(1e-12);
    }
}

// Precision. A pair is computed in the model's type T. In float, a pair "at risk" is computed
// again in double: its 2D covariance overflowed or is not finite, its determinant is at or below
// the float floor or cancels (det < kCancel * a * c: a long thin needle, whose float conic was
// 40 % off at 3000 px), its covariance's rounding is large against its footprint (kCovError), or
// its pixel centre would round by more than kPixelError. Such pairs are rare in a trained model
// (eps2d = 0.3 keeps det >= 0.09), so the float path keeps its speed (double throughout cost
// 5-8 % per render at 128 px). Results are stored in T; a pair whose double results still do not
// fit T (a conic that overflows, a centre beyond T's range) is culled with zeros stored, as
// projection.narrow does. The backward makes the same choice from the same float values.
constexpr double kCancel = 1e-3;

// (4) the pixel centre's rounding: camera-space x, y carry ~eps * (|R mean| + |t|) of error, which
// the focal over depth scales into pixels (a camera of focal 2.7e8 put a splat 16 px off).
constexpr double kPixelError = 0.01;

// (5) the 3D covariance's rounding: its entries carry ~eps * (largest scale)^2 of error, which the
// Jacobian carries into the 2D covariance whatever the Gaussian's orientation; it must stay below
// kCovError of a lower bound of the footprint's smallest eigenvalue that rounding cannot fake,
// (smallest scale * min(fx, fy) / z)^2 + eps2d (J J^T >= (f / z)^2 I). A needle with scales
// (39, 3e7, 5590) had a float covariance with a negative eigenvalue and a conic 1e7 times off,
// and a float determinant that looked harmless.
constexpr double kCovError = 1e-3;

template <typename P>
inline bool needs_double(const Pair<P>& q, const Cam<P>& cam, const P* mean, P smax2, P smin2, P eps2d) {
    if (std::is_same<P, double>::value || !q.in_depth) return false;
    if (!(std::isfinite(q.a) && std::isfinite(q.b) && std::isfinite(q.c) && std::isfinite(q.det)) ||
        q.det <= P(kFloatDetFloor) || q.det < P(kCancel) * q.a * q.c)
        return true;
    const P eps = std::numeric_limits<P>::epsilon(), gain = std::max(cam.fx, cam.fy) * q.inv_zs;
    const P low = std::min(cam.fx, cam.fy) * q.inv_zs;
    if (P(8) * eps * smax2 * gain * gain > P(kCovError) * (smin2 * low * low + eps2d)) return true;
    const P magnitude = std::abs(mean[0]) + std::abs(mean[1]) + std::abs(mean[2]) + cam.t_abs;
    return P(4) * eps * magnitude * gain > P(kPixelError);
}

// The pair of Gaussian n and a camera done again in double, its covariance rebuilt from the
// model's T quaternion and scales (what needs_double sends here, forward and backward alike);
// gmean receives the mean in double.
template <typename T>
inline Pair<double> pair_double(const T* quats, const T* scales, int64_t n, const T* mean, const Cam<double>& cam,
                                const Settings& s, double* gmean) {
    const double q[4] = {double(quats[n * 4]), double(quats[n * 4 + 1]), double(quats[n * 4 + 2]), double(quats[n * 4 + 3])};
    const double sc[3] = {double(scales[n * 3]), double(scales[n * 3 + 1]), double(scales[n * 3 + 2])};
    double qn[4], qnorm, R[9], cov[6];
    gaussian_cov(q, sc, qn, qnorm, R, cov);
    for (int j = 0; j < 3; ++j) gmean[j] = double(mean[j]);
    Pair<double> qd;
    qd.compute(cam, gmean, cov, s);
    return qd;
}

template <typename T>
void forward(const Settings& s, const T* means, const T* quats, const T* scales, const T* sh,
             const T* viewmats, const T* Ks, T* means2d, T* conics, T* depths, T* comp, T* colors,
             int32_t* radii, int32_t* rects, uint8_t* valid, int n_threads) {
    const std::vector<Cam<T>> cams = load_cameras<T>(s, viewmats, Ks);
    const std::vector<Cam<double>> gcams = load_cameras<double>(s, viewmats, Ks);
    const int64_t tiles_x = (s.width + s.tile - 1) / s.tile, tiles_y = (s.height + s.tile - 1) / s.tile;
    const int n_basis = s.sh_degree >= 0 ? int((s.sh_degree + 1) * (s.sh_degree + 1)) : 0;
    // Dividing by a power of two is exact as a product, so the common T = 16 avoids 4 divisions.
    const bool tile_pow2 = (s.tile & (s.tile - 1)) == 0;
    const double inv_tile = 1.0 / double(s.tile);
    parallel_blocks(s.N, kGaussians, n_threads, [&](int64_t n0, int64_t n1) {
        GaussianBlock<T> blk;
        blk.load(n0, n1, quats, scales);
        // Writes pair g's outputs from q (in P = T or double); returns false, writing nothing,
        // when q is a float pair that must be done again in double.
        auto emit = [&](const auto& q, const auto& cam, const auto* mean, decltype(q.a) smax2, decltype(q.a) smin2,
                        int64_t g) -> bool {
            using P = typename std::decay<decltype(q.a)>::type;
            if (needs_double(q, cam, mean, smax2, smin2, P(s.eps2d))) return false;
            // x / z before the focal: a centre beyond T's range overflows only if the result does
            const P u = cam.fx * (q.p[0] * q.inv_zs) + cam.cx, v = cam.fy * (q.p[1] * q.inv_zs) + cam.cy;
            const P inv_det = P(1) / q.det_s;
            const P det_raw = q.ok ? q.a_raw * q.c_raw - q.b * q.b : P(0);
            const T out2[2] = {T(u), T(v)};
            const T outq[3] = {T(q.c * inv_det), T(-q.b * inv_det), T(q.a * inv_det)};
            const T outc = T(std::sqrt(std::max(det_raw * inv_det, P(1e-12))));
            const bool fits = std::isfinite(out2[0]) && std::isfinite(out2[1]) && std::isfinite(outq[0]) &&
                              std::isfinite(outq[1]) && std::isfinite(outq[2]) && std::isfinite(outc);
            // A pair whose outputs do not fit T is culled: in double they would not fit either
            // (the conic and the centre are the same numbers, only rounded differently).
            means2d[g * 2] = fits ? out2[0] : T(0);
            means2d[g * 2 + 1] = fits ? out2[1] : T(0);
            for (int k = 0; k < 3; ++k) conics[g * 3 + k] = fits ? outq[k] : T(0);
            comp[g] = fits ? outc : T(0);
            depths[g] = T(q.p[2]);
            // Radius and tiles (no gradient), in the order of operations of projection.py.
            const P mid = P(0.5) * (q.a + q.c);
            const P lam = mid + std::sqrt(std::max(mid * mid - q.det, P(0.1)));
            P radius = std::ceil(P(3) * std::sqrt(lam));
            bool ok = q.ok && fits && std::isfinite(radius) && radius > P(s.radius_clip);
            radius = ok ? std::min(radius, P(1 << 30)) : P(0);
            int32_t* r = rects + g * 4;
            const double rr = double(radius);
            auto rng = [&](double center, int64_t n_t, int32_t* out) {
                const double T_ = double(s.tile);
                double lo = tile_pow2 ? std::floor((center - rr) * inv_tile) : std::floor((center - rr) / T_);
                double hi = tile_pow2 ? std::floor((center + rr + T_ - 1) * inv_tile)
                                      : std::floor((center + rr + T_ - 1) / T_);
                lo = std::min(std::max(lo, 0.0), double(n_t));
                hi = std::min(std::max(hi, 0.0), double(n_t));
                if (std::isnan(lo)) lo = 0;  // torch.clamp keeps NaN; such pairs are not ok anyway
                if (std::isnan(hi)) hi = 0;
                out[0] = int32_t(lo);
                out[1] = int32_t(hi);
            };
            rng(double(means2d[g * 2]), tiles_x, r);
            rng(double(means2d[g * 2 + 1]), tiles_y, r + 2);
            ok = ok && r[1] > r[0] && r[3] > r[2];
            if (!ok) r[0] = r[1] = r[2] = r[3] = 0;
            radii[g] = ok ? int32_t(radius) : 0;
            valid[g] = ok ? 1 : 0;
            return true;
        };
        // Cameras outside, Gaussians inside: each output row is written sequentially.
        for (int64_t c = 0; c < s.C; ++c) {
            const Cam<T>& cam = cams[c];
            for (int64_t n = n0; n < n1; ++n) {
                const T* mean = means + n * 3;
                const int64_t g = c * s.N + n;
                Pair<T> q;
                q.compute(cam, mean, blk.cov[n - n0], s);
                if (!emit(q, cam, mean, blk.smax2[n - n0], blk.smin2[n - n0], g)) {
                    double gmean[3];
                    const Pair<double> qd = pair_double(quats, scales, n, mean, gcams[c], s, gmean);
                    emit(qd, gcams[c], gmean, 0.0, 0.0, g);
                }
                if (n_basis) {
                    T d[3];
                    for (int j = 0; j < 3; ++j) d[j] = mean[j] - cam.center[j];
                    const T len = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
                    const T inv = T(1) / std::max(len, T(1e-12));
                    const T dir[3] = {d[0] * inv, d[1] * inv, d[2] * inv};
                    const T* coef = sh + n * s.K * 3;
                    switch (s.sh_degree) {  // the degree as a constant lets the compiler unroll
                        case 0: sh_color<T, 0>(dir, coef, colors + g * 3); break;
                        case 1: sh_color<T, 1>(dir, coef, colors + g * 3); break;
                        case 2: sh_color<T, 2>(dir, coef, colors + g * 3); break;
                        default: sh_color<T, 3>(dir, coef, colors + g * 3); break;
                    }
                }
            }
        }
    });
}

// Antialiasing's compensation = sqrt(max(r, 1e-12)), r = det_raw / det, backward: adds to the
// gradients of a_raw, c_raw and b. r's derivatives in closed form: with det = det_raw + e (a_raw +
// c_raw) + e^2, dr/da_raw = e (c_raw c + b^2) / det^2, dr/dc_raw = e (a_raw a + b^2) / det^2 and
// dr/db = -2 b e (a_raw + c_raw + e) / det^2. Taken through det_raw and det apart, the two terms
// cancel to a few ulp of 1/a for a splat much wider than eps2d (a float32 splat 1e7 px wide got
// gradients 1e3-1e11 times too large), and det^2 overflows.
template <typename P>
inline void compensation_backward(const Pair<P>& q, double gcp, double eps2d, P& da_raw, P& dc_raw, P& db) {
    const P r = (q.a_raw * q.c_raw - q.b * q.b) / q.det_s;
    if (!(r >= P(1e-12))) return;
    const P e = P(eps2d), inv_det = P(1) / q.det_s;
    const P dr = P(gcp) * P(0.5) / std::sqrt(r) * e * inv_det;
    da_raw += dr * ((q.c_raw * inv_det) * q.c + (q.b * inv_det) * q.b);
    dc_raw += dr * ((q.a_raw * inv_det) * q.a + (q.b * inv_det) * q.b);
    db -= P(2) * dr * (q.b * inv_det) * (q.a_raw + q.c_raw + e);
}

// Backward of one pair's geometry (P = T or double): adds to the mean's and the covariance's
// gradients (accumulated in double).
template <typename P>
inline void pair_backward(const Pair<P>& q, const Cam<P>& cam, double gu, double gv, double gq0, double gq1,
                          double gq2, double gd, double gcp, double eps2d, double* dm, double* dcov) {
    P dp[3] = {0, 0, P(gd)}, dzs = 0;
    // means2d = (fx x / zs + cx, fy y / zs + cy)
    dp[0] += P(gu) * cam.fx / q.zs;
    dp[1] += P(gv) * cam.fy / q.zs;
    dzs -= (P(gu) * cam.fx * q.p[0] + P(gv) * cam.fy * q.p[1]) / (q.zs * q.zs);
    // conics = (c, -b, a) / det_s
    P da = P(gq2) / q.det_s, db = -P(gq1) / q.det_s, dc = P(gq0) / q.det_s;
    if (q.ok) {  // d(conic)/d(det) = -conic / det
        P ddet = -(P(gq0) * q.c - P(gq1) * q.b + P(gq2) * q.a) / (q.det_s * q.det_s);
        if (!std::isfinite(q.det_s * q.det_s)) {  // det^2 overflows float beyond 1.8e19 (a splat ~1e5 px wide)
            const P inv_det = P(1) / q.det_s;
            ddet = -(P(gq0) * (q.c * inv_det) - P(gq1) * (q.b * inv_det) + P(gq2) * (q.a * inv_det)) * inv_det;
        }
        da += ddet * q.c;
        dc += ddet * q.a;
        db -= P(2) * ddet * q.b;
    }
    P da_raw = 0, dc_raw = 0;
    if (q.ok && gcp != 0.0) compensation_backward(q, gcp, eps2d, da_raw, dc_raw, db);
    da += da_raw;
    dc += dc_raw;
    // a = jw0^T S jw0, b = jw0^T S jw1, c = jw1^T S jw1 (S symmetric)
    const P* j0 = q.jw0;
    const P* j1 = q.jw1;
    dcov[0] += double(da * j0[0] * j0[0] + db * j0[0] * j1[0] + dc * j1[0] * j1[0]);
    dcov[3] += double(da * j0[1] * j0[1] + db * j0[1] * j1[1] + dc * j1[1] * j1[1]);
    dcov[5] += double(da * j0[2] * j0[2] + db * j0[2] * j1[2] + dc * j1[2] * j1[2]);
    dcov[1] += double(P(2) * da * j0[0] * j0[1] + db * (j0[0] * j1[1] + j1[0] * j0[1]) + P(2) * dc * j1[0] * j1[1]);
    dcov[2] += double(P(2) * da * j0[0] * j0[2] + db * (j0[0] * j1[2] + j1[0] * j0[2]) + P(2) * dc * j1[0] * j1[2]);
    dcov[4] += double(P(2) * da * j0[1] * j0[2] + db * (j0[1] * j1[2] + j1[1] * j0[2]) + P(2) * dc * j1[1] * j1[2]);
    P dj0[3], dj1[3];
    for (int i = 0; i < 3; ++i) {
        dj0[i] = P(2) * da * q.s0[i] + db * q.s1[i];
        dj1[i] = db * q.s0[i] + P(2) * dc * q.s1[i];
    }
    // jw0 = (fx / zs) R0 - (fx xz / zs) R2; jw1 likewise with fy, yz, R1
    P dA0 = 0, dB0 = 0, dA1 = 0, dB1 = 0;
    for (int j = 0; j < 3; ++j) {
        dA0 += dj0[j] * cam.R[j];
        dB0 -= dj0[j] * cam.R[6 + j];
        dA1 += dj1[j] * cam.R[3 + j];
        dB1 -= dj1[j] * cam.R[6 + j];
    }
    const P zs2 = q.zs * q.zs;
    dzs -= (dA0 * cam.fx + dB0 * cam.fx * q.xz + dA1 * cam.fy + dB1 * cam.fy * q.yz) / zs2;
    const P dxz = dB0 * cam.fx / q.zs, dyz = dB1 * cam.fy / q.zs;
    // x/z and y/z clamps pass the gradient inside [lo, hi] (torch.clamp's rule)
    if (q.raw_xz >= cam.lo_x && q.raw_xz <= cam.hi_x) {
        dp[0] += dxz / q.zs;
        dzs -= dxz * q.p[0] / zs2;
    }
    if (q.raw_yz >= cam.lo_y && q.raw_yz <= cam.hi_y) {
        dp[1] += dyz / q.zs;
        dzs -= dyz * q.p[1] / zs2;
    }
    if (q.in_depth) dp[2] += dzs;
    for (int j = 0; j < 3; ++j)
        dm[j] += double(cam.R[j] * dp[0] + cam.R[3 + j] * dp[1] + cam.R[6 + j] * dp[2]);
}

template <typename T>
void backward(const Settings& s, const T* means, const T* quats, const T* scales, const T* sh,
              const T* viewmats, const T* Ks, const T* g_means2d, const T* g_conics, const T* g_depths,
              const T* g_comp, const T* g_colors, T* d_means, T* d_quats, T* d_scales, T* d_sh,
              int n_threads) {
    const std::vector<Cam<T>> cams = load_cameras<T>(s, viewmats, Ks);
    const std::vector<Cam<double>> gcams = load_cameras<double>(s, viewmats, Ks);
    const int n_basis = s.sh_degree >= 0 ? int((s.sh_degree + 1) * (s.sh_degree + 1)) : 0;
    parallel_blocks(s.N, kGaussians, n_threads, [&](int64_t n0, int64_t n1) {
        GaussianBlock<T> blk;
        blk.load(n0, n1, quats, scales);
        // Gradients add up in double: a pair done in double may pass a gradient beyond float.
        double dmeans[kGaussians][3] = {}, dcovs[kGaussians][6] = {};
        // Cameras outside, Gaussians inside (rows read sequentially); each Gaussian's gradient
        // still adds up over the cameras in camera order, in this one thread.
        for (int64_t c = 0; c < s.C; ++c) {
            const Cam<T>& cam = cams[c];
            for (int64_t n = n0; n < n1; ++n) {
                const T* mean = means + n * 3;
                double* dm = dmeans[n - n0];
                T* dsh = d_sh ? d_sh + n * s.K * 3 : nullptr;
                const int64_t g = c * s.N + n;
                const double gu = g_means2d[g * 2], gv = g_means2d[g * 2 + 1];
                const double gq0 = g_conics[g * 3], gq1 = g_conics[g * 3 + 1], gq2 = g_conics[g * 3 + 2];
                const double gd = g_depths[g], gcp = g_comp[g];
                const bool geo = gu != 0.0 || gv != 0.0 || gq0 != 0.0 || gq1 != 0.0 || gq2 != 0.0 || gd != 0.0 ||
                                 gcp != 0.0;
                if (n_basis) {
                    const T* gc = g_colors + g * 3;
                    if (gc[0] != T(0) || gc[1] != T(0) || gc[2] != T(0)) {
                        T dmc[3] = {T(0), T(0), T(0)};  // the colour's share of the mean's gradient
                        sh_backward(int(s.sh_degree), n_basis, cam, mean, sh + n * s.K * 3, gc, dsh, dmc);
                        for (int j = 0; j < 3; ++j) dm[j] += double(dmc[j]);
                    }
                }
                if (!geo) continue;  // culled, occluded or unused: nothing reaches this pair
                Pair<T> q;
                q.compute(cam, mean, blk.cov[n - n0], s);
                // the forward's choice (culled pairs, whose outputs did not fit, get no gradient)
                if (!needs_double(q, cam, mean, blk.smax2[n - n0], blk.smin2[n - n0], T(s.eps2d))) {
                    pair_backward(q, cam, gu, gv, gq0, gq1, gq2, gd, gcp, s.eps2d, dm, dcovs[n - n0]);
                } else {
                    double gmean[3];
                    pair_backward(pair_double(quats, scales, n, mean, gcams[c], s, gmean), gcams[c], gu, gv, gq0, gq1,
                                  gq2, gd, gcp, s.eps2d, dm, dcovs[n - n0]);
                }
            }
        }
        for (int64_t n = n0; n < n1; ++n) {
            const int64_t i = n - n0;
            for (int j = 0; j < 3; ++j) d_means[n * 3 + j] = T(dmeans[i][j]);
            const T dcov[6] = {T(dcovs[i][0]), T(dcovs[i][1]), T(dcovs[i][2]), T(dcovs[i][3]), T(dcovs[i][4]),
                               T(dcovs[i][5])};  // beyond T's range: Inf, and the caller raises
            cov_backward(blk.qn[i], blk.qnorm[i], blk.R[i], scales + n * 3, dcov, d_quats + n * 4, d_scales + n * 3);
        }
    });
}

}  // namespace

extern "C" {

// Settings as plain arrays keep the ctypes signature short: ints = C, N, width, height, tile, K,
// sh_degree (-1: no colours); reals = near, far, eps2d, radius_clip.
#define MVGS_PROJECT(T, SUFFIX)                                                                   \
    void mvgs_project_forward_##SUFFIX(const int64_t* ints, const double* reals, const T* means,   \
                                       const T* quats, const T* scales, const T* sh,              \
                                       const T* viewmats, const T* Ks, T* means2d, T* conics,      \
                                       T* depths, T* comp, T* colors, int32_t* radii,             \
                                       int32_t* rects, uint8_t* valid, int n_threads) {           \
        const Settings s{ints[0], ints[1], ints[2], ints[3], ints[4], ints[5], ints[6],           \
                         reals[0], reals[1], reals[2], reals[3]};                                 \
        forward<T>(s, means, quats, scales, sh, viewmats, Ks, means2d, conics, depths, comp,      \
                   colors, radii, rects, valid, n_threads);                                       \
    }                                                                                             \
    void mvgs_project_backward_##SUFFIX(const int64_t* ints, const double* reals, const T* means,  \
                                        const T* quats, const T* scales, const T* sh,             \
                                        const T* viewmats, const T* Ks, const T* g_means2d,       \
                                        const T* g_conics, const T* g_depths, const T* g_comp,    \
                                        const T* g_colors, T* d_means, T* d_quats, T* d_scales,   \
                                        T* d_sh, int n_threads) {                                 \
        const Settings s{ints[0], ints[1], ints[2], ints[3], ints[4], ints[5], ints[6],           \
                         reals[0], reals[1], reals[2], reals[3]};                                 \
        backward<T>(s, means, quats, scales, sh, viewmats, Ks, g_means2d, g_conics, g_depths,     \
                    g_comp, g_colors, d_means, d_quats, d_scales, d_sh, n_threads);               \
    }

MVGS_PROJECT(float, f32)
MVGS_PROJECT(double, f64)

#undef MVGS_PROJECT

}  // extern "C"
