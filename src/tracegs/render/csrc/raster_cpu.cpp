// CPU rasteriser for 3D Gaussian splatting: projection, tile binning, alpha blending and their
// explicit backward passes. Numerics follow gsplat's "classic" 3DGS kernels (eps2d blur without
// opacity compensation, alpha = min(0.99, o * exp(-sigma)), skip alpha < 1/255, stop before a
// Gaussian would take transmittance to <= 1e-4); see docs/RASTERIZER.md.
//
// N: Gaussians, I: tile-Gaussian intersections, H x W: image, 16 x 16 pixel tiles.
//
// Parallelism: one OpenMP task per Gaussian (projection) or per tile (blending). Every reduction
// runs in a fixed order that does not depend on the thread count: the blending backward writes one
// gradient row per intersection and a second pass sums each Gaussian's rows in tile order.

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/ones.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr int kTile = 16;
constexpr float kMaxAlpha = 0.99f;
constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kTransmittanceThreshold = 1e-4f;
// Slack (pixels) added to the alpha >= 1/255 box so that float rounding in the per-pixel alpha can
// never put a contributing pixel outside the tiles a Gaussian was binned to.
constexpr float kBoxSlack = 1e-2f;
constexpr int kGradStride = 10;  // per intersection: mean2d(2), conic(3), color(3), opacity, depth

// A tile row of 16 pixels as kParts GCC/clang vectors of the target's own width (1 x AVX-512,
// 2 x AVX2, 4 x SSE or NEON), the blending loops running over the parts one after another: every
// lane computes the same operations on any target, so the passes agree bit for bit with each other
// and across builds. (One 16-lane vector on AVX2 was ~2.6x slower than the split: GCC
// expands its comparisons and selects lane by lane with branches, and the backward's accumulators
// spill from AVX2's 16 registers.)
#if defined(__AVX512F__)
constexpr int kVectorBytes = 64;
#elif defined(__AVX__)
constexpr int kVectorBytes = 32;
#else
constexpr int kVectorBytes = 16;  // SSE, NEON
#endif
constexpr int kLanes = kVectorBytes / static_cast<int>(sizeof(float));
constexpr int kParts = kTile / kLanes;
typedef float vf __attribute__((vector_size(kVectorBytes)));
typedef int32_t vi __attribute__((vector_size(kVectorBytes)));

inline vf splat(float s) { return vf{} + s; }
inline vi splati(int32_t s) { return vi{} + s; }
inline vf select(vi mask, vf a, vf b) { return mask ? a : b; }

// Column c of a tile row is lane c % kLanes of part c / kLanes (subscripted in place: clang binds no
// reference to a vector's element)

// s plus the lanes of v, always in the same order (deterministic)
inline float hsum(float s, vf v) {
    for (int i = 0; i < kLanes; ++i) s += v[i];
    return s;
}

// exp(x) for x <= 0, lane-wise. Cephes-style range reduction + degree-6 polynomial (~1 ulp);
// libm's expf would not vectorise without -ffast-math.
inline vf exp_neg(vf x) {
    x = select(x > -87.0f, x, splat(-87.0f));
    const vf round_magic = splat(12582912.0f);  // 1.5 * 2^23: adding and subtracting rounds to int
    const vf n = (x * 1.44269504088896341f + round_magic) - round_magic;
    const vf r = x - n * 0.693359375f + n * 2.12194440e-4f;
    const vf r2 = r * r;
    vf p = splat(1.9875691500e-4f);
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r2 + r + 1.0f;
    const vi bits = (__builtin_convertvector(n, vi) + 127) << 23;
    vf scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
}

struct Camera {
    float R[9];  // world-to-camera rotation, row-major
    float t[3];
    float fx, fy, cx, cy;
    float lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;  // gsplat's 1.3 x FOV clamp of the Jacobian
    int width, height;
};

Camera make_camera(const at::Tensor& viewmat, const at::Tensor& K, int width, int height) {
    auto v = viewmat.accessor<float, 2>();
    auto k = K.accessor<float, 2>();
    Camera c;
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) c.R[i * 3 + j] = v[i][j];
        c.t[i] = v[i][3];
    }
    c.fx = k[0][0];
    c.fy = k[1][1];
    c.cx = k[0][2];
    c.cy = k[1][2];
    const float tan_fovx = 0.5f * width / c.fx;
    const float tan_fovy = 0.5f * height / c.fy;
    c.lim_x_pos = (width - c.cx) / c.fx + 0.3f * tan_fovx;
    c.lim_x_neg = c.cx / c.fx + 0.3f * tan_fovx;
    c.lim_y_pos = (height - c.cy) / c.fy + 0.3f * tan_fovy;
    c.lim_y_neg = c.cy / c.fy + 0.3f * tan_fovy;
    c.width = width;
    c.height = height;
    return c;
}

// Rotation matrix (row-major) of a unit quaternion (w, x, y, z).
inline void quat_to_rotmat(const float q[4], float R[9]) {
    const float w = q[0], x = q[1], y = q[2], z = q[3];
    R[0] = 1.f - 2.f * (y * y + z * z);
    R[1] = 2.f * (x * y - w * z);
    R[2] = 2.f * (x * z + w * y);
    R[3] = 2.f * (x * y + w * z);
    R[4] = 1.f - 2.f * (x * x + z * z);
    R[5] = 2.f * (y * z - w * x);
    R[6] = 2.f * (x * z - w * y);
    R[7] = 2.f * (y * z + w * x);
    R[8] = 1.f - 2.f * (x * x + y * y);
}

// Everything the projection of one Gaussian computes; the backward pass recomputes it rather than
// storing 40 floats per Gaussian.
struct ProjState {
    float pc[3];    // camera-frame mean
    float qn[4];    // normalised quaternion
    float qnorm;
    float Rq[9];    // rotation of the Gaussian
    float V[9];     // camera-frame R diag(s)
    float J[4];     // J00, J02, J11, J12 (J01 = J10 = 0)
    float P[6];     // J V, rows of the 2 x 3 "square root" of the 2D covariance
    float tx, ty;   // clamped x, y used in the Jacobian
    bool in_x, in_y;
    float cov[3];   // blurred 2D covariance (a, b, c)
};

// Returns false if the Gaussian is outside the near/far range.
inline bool project_one(const Camera& cam, const float* mean, const float* quat, const float* scale,
                        float eps2d, float near_plane, float far_plane, ProjState& s) {
    const float* R = cam.R;
    for (int i = 0; i < 3; ++i)
        s.pc[i] = R[i * 3] * mean[0] + R[i * 3 + 1] * mean[1] + R[i * 3 + 2] * mean[2] + cam.t[i];
    const float z = s.pc[2];
    if (!(z >= near_plane && z <= far_plane)) return false;

    s.qnorm = std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
    for (int i = 0; i < 4; ++i) s.qn[i] = quat[i] / s.qnorm;
    quat_to_rotmat(s.qn, s.Rq);
    float M[9];
    for (int j = 0; j < 3; ++j)
        for (int m = 0; m < 3; ++m) M[j * 3 + m] = s.Rq[j * 3 + m] * scale[m];
    for (int i = 0; i < 3; ++i)
        for (int m = 0; m < 3; ++m)
            s.V[i * 3 + m] = R[i * 3] * M[m] + R[i * 3 + 1] * M[3 + m] + R[i * 3 + 2] * M[6 + m];

    const float rz = 1.f / z;
    const float u = s.pc[0] * rz, v = s.pc[1] * rz;
    s.in_x = u >= -cam.lim_x_neg && u <= cam.lim_x_pos;
    s.in_y = v >= -cam.lim_y_neg && v <= cam.lim_y_pos;
    s.tx = z * std::min(cam.lim_x_pos, std::max(-cam.lim_x_neg, u));
    s.ty = z * std::min(cam.lim_y_pos, std::max(-cam.lim_y_neg, v));
    s.J[0] = cam.fx * rz;
    s.J[1] = -cam.fx * s.tx * rz * rz;
    s.J[2] = cam.fy * rz;
    s.J[3] = -cam.fy * s.ty * rz * rz;
    for (int m = 0; m < 3; ++m) {
        s.P[m] = s.J[0] * s.V[m] + s.J[1] * s.V[6 + m];
        s.P[3 + m] = s.J[2] * s.V[3 + m] + s.J[3] * s.V[6 + m];
    }
    s.cov[0] = s.P[0] * s.P[0] + s.P[1] * s.P[1] + s.P[2] * s.P[2] + eps2d;
    s.cov[1] = s.P[0] * s.P[3] + s.P[1] * s.P[4] + s.P[2] * s.P[5];
    s.cov[2] = s.P[3] * s.P[3] + s.P[4] * s.P[4] + s.P[5] * s.P[5] + eps2d;
    return true;
}

}  // namespace

// Projection forward. Returns means2d [N, 2], conics [N, 3], depths [N], radii [N] (int32, 0 =
// culled) and extents [N, 2]: the half-widths (pixels) of the box holding every pixel where the
// Gaussian's alpha can reach 1/255 (-1 when it never can), used only for tile binning.
std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                           at::Tensor opacities, at::Tensor viewmat, at::Tensor K,
                                           int64_t width, int64_t height, double near_plane,
                                           double far_plane, double eps2d, int64_t num_threads) {
    const int64_t N = means.size(0);
    const Camera cam = make_camera(viewmat, K, width, height);
    auto opts = means.options();
    auto means2d = at::zeros({N, 2}, opts);
    auto conics = at::zeros({N, 3}, opts);
    auto depths = at::zeros({N}, opts);
    auto radii = at::zeros({N}, opts.dtype(at::kInt));
    auto extents = at::full({N, 2}, -1.0f, opts);
    const float* pm = means.data_ptr<float>();
    const float* pq = quats.data_ptr<float>();
    const float* ps = scales.data_ptr<float>();
    const float* po = opacities.data_ptr<float>();
    float* om = means2d.data_ptr<float>();
    float* oc = conics.data_ptr<float>();
    float* od = depths.data_ptr<float>();
    int32_t* orad = radii.data_ptr<int32_t>();
    float* oe = extents.data_ptr<float>();
    const float feps = static_cast<float>(eps2d), fnear = static_cast<float>(near_plane),
                ffar = static_cast<float>(far_plane);

#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t g = 0; g < N; ++g) {
        ProjState s;
        if (!project_one(cam, pm + 3 * g, pq + 4 * g, ps + 3 * g, feps, fnear, ffar, s)) continue;
        const float a = s.cov[0], b = s.cov[1], c = s.cov[2];
        const float det = a * c - b * b;
        if (!(det > 0.f)) continue;
        const float rz = 1.f / s.pc[2];
        const float mx = cam.fx * s.pc[0] * rz + cam.cx;
        const float my = cam.fy * s.pc[1] * rz + cam.cy;
        const float half = 0.5f * (a + c);
        const float v1 = half + std::sqrt(std::max(0.01f, half * half - det));
        const float radius = std::ceil(3.f * std::sqrt(v1));
        if (radius <= 0.f) continue;
        if (mx + radius <= 0.f || mx - radius >= cam.width || my + radius <= 0.f || my - radius >= cam.height)
            continue;
        const float inv = 1.f / det;
        om[2 * g] = mx;
        om[2 * g + 1] = my;
        oc[3 * g] = c * inv;
        oc[3 * g + 1] = -b * inv;
        oc[3 * g + 2] = a * inv;
        od[g] = s.pc[2];
        orad[g] = static_cast<int32_t>(radius);
        const float o = po[g];
        if (o >= kAlphaThreshold) {
            // alpha >= 1/255  <=>  d^T conic d <= 2 log(255 o); the ellipse's x half-width is
            // sqrt(2 log(255 o) cov_xx).
            const float m = 2.f * std::log(255.f * o);
            oe[2 * g] = std::sqrt(std::max(m, 0.f) * a);
            oe[2 * g + 1] = std::sqrt(std::max(m, 0.f) * c);
        }
    }
    return {means2d, conics, depths, radii, extents};
}

// Projection backward: from dL/d(means2d, conics, depths) to dL/d(means, quats, scales).
std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                            at::Tensor viewmat, at::Tensor K, at::Tensor radii,
                                            at::Tensor conics, at::Tensor v_means2d,
                                            at::Tensor v_conics, at::Tensor v_depths, int64_t width,
                                            int64_t height, double eps2d, int64_t num_threads) {
    const int64_t N = means.size(0);
    const Camera cam = make_camera(viewmat, K, width, height);
    auto v_means = at::zeros_like(means);
    auto v_quats = at::zeros_like(quats);
    auto v_scales = at::zeros_like(scales);
    const float* pm = means.data_ptr<float>();
    const float* pq = quats.data_ptr<float>();
    const float* ps = scales.data_ptr<float>();
    const int32_t* prad = radii.data_ptr<int32_t>();
    const float* pcon = conics.data_ptr<float>();
    const float* gm = v_means2d.data_ptr<float>();
    const float* gc = v_conics.data_ptr<float>();
    const float* gd = v_depths.data_ptr<float>();
    float* vm = v_means.data_ptr<float>();
    float* vq = v_quats.data_ptr<float>();
    float* vs = v_scales.data_ptr<float>();
    const float feps = static_cast<float>(eps2d);
    const float* R = cam.R;

#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t g = 0; g < N; ++g) {
        if (prad[g] <= 0) continue;
        ProjState s;
        project_one(cam, pm + 3 * g, pq + 4 * g, ps + 3 * g, feps, -INFINITY, INFINITY, s);
        const float cA = pcon[3 * g], cB = pcon[3 * g + 1], cC = pcon[3 * g + 2];
        const float vA = gc[3 * g], vB = 0.5f * gc[3 * g + 1], vC = gc[3 * g + 2];
        // conic = cov^-1  =>  dL/dcov = -conic (dL/dconic) conic, with the off-diagonal gradient
        // split over the two symmetric entries.
        const float q00 = cA * vA + cB * vB, q01 = cA * vB + cB * vC;
        const float q10 = cB * vA + cC * vB, q11 = cB * vB + cC * vC;
        const float g00 = -(q00 * cA + q01 * cB), g01 = -(q00 * cB + q01 * cC);
        const float g11 = -(q10 * cB + q11 * cC);
        // cov = P P^T  =>  dL/dP = 2 G P
        float vP[6];
        for (int m = 0; m < 3; ++m) {
            vP[m] = 2.f * (g00 * s.P[m] + g01 * s.P[3 + m]);
            vP[3 + m] = 2.f * (g01 * s.P[m] + g11 * s.P[3 + m]);
        }
        // P = J V
        float vJ00 = 0.f, vJ02 = 0.f, vJ11 = 0.f, vJ12 = 0.f;
        for (int m = 0; m < 3; ++m) {
            vJ00 += vP[m] * s.V[m];
            vJ02 += vP[m] * s.V[6 + m];
            vJ11 += vP[3 + m] * s.V[3 + m];
            vJ12 += vP[3 + m] * s.V[6 + m];
        }
        float vV[9];
        for (int m = 0; m < 3; ++m) {
            vV[m] = s.J[0] * vP[m];
            vV[3 + m] = s.J[2] * vP[3 + m];
            vV[6 + m] = s.J[1] * vP[m] + s.J[3] * vP[3 + m];
        }
        // V = Rcam M, M = Rq diag(s)
        const float* sc = ps + 3 * g;
        float vR[9], v_s[3] = {0.f, 0.f, 0.f};
        for (int j = 0; j < 3; ++j)
            for (int m = 0; m < 3; ++m) {
                const float vM = R[j] * vV[m] + R[3 + j] * vV[3 + m] + R[6 + j] * vV[6 + m];
                vR[j * 3 + m] = vM * sc[m];
                v_s[m] += vM * s.Rq[j * 3 + m];
            }
        const float w = s.qn[0], x = s.qn[1], y = s.qn[2], z = s.qn[3];
        float vqn[4];
        vqn[0] = 2.f * (-z * vR[1] + y * vR[2] + z * vR[3] - x * vR[5] - y * vR[6] + x * vR[7]);
        vqn[1] = 2.f * (y * vR[1] + z * vR[2] + y * vR[3] - 2.f * x * vR[4] - w * vR[5] + z * vR[6] +
                        w * vR[7] - 2.f * x * vR[8]);
        vqn[2] = 2.f * (-2.f * y * vR[0] + x * vR[1] + w * vR[2] + x * vR[3] + z * vR[5] - w * vR[6] +
                        z * vR[7] - 2.f * y * vR[8]);
        vqn[3] = 2.f * (-2.f * z * vR[0] - w * vR[1] + x * vR[2] + w * vR[3] - 2.f * z * vR[4] +
                        y * vR[5] + x * vR[6] + y * vR[7]);
        const float dot = vqn[0] * w + vqn[1] * x + vqn[2] * y + vqn[3] * z;
        for (int i = 0; i < 4; ++i) vq[4 * g + i] = (vqn[i] - s.qn[i] * dot) / s.qnorm;
        for (int m = 0; m < 3; ++m) vs[3 * g + m] = v_s[m];

        // camera-frame mean: through means2d, depth and the Jacobian
        const float px = s.pc[0], py = s.pc[1], pz = s.pc[2];
        const float rz = 1.f / pz, rz2 = rz * rz, rz3 = rz2 * rz;
        const float vmx = gm[2 * g], vmy = gm[2 * g + 1];
        float vpx = cam.fx * rz * vmx;
        float vpy = cam.fy * rz * vmy;
        float vpz = -(cam.fx * px * vmx + cam.fy * py * vmy) * rz2 + gd[g];
        vpz += -cam.fx * rz2 * vJ00 - cam.fy * rz2 * vJ11;
        if (s.in_x) {
            vpx += -cam.fx * rz2 * vJ02;
            vpz += 2.f * cam.fx * s.tx * rz3 * vJ02;
        } else {
            vpz += cam.fx * s.tx * rz3 * vJ02;
        }
        if (s.in_y) {
            vpy += -cam.fy * rz2 * vJ12;
            vpz += 2.f * cam.fy * s.ty * rz3 * vJ12;
        } else {
            vpz += cam.fy * s.ty * rz3 * vJ12;
        }
        for (int j = 0; j < 3; ++j) vm[3 * g + j] = R[j] * vpx + R[3 + j] * vpy + R[6 + j] * vpz;
    }
    return {v_means, v_quats, v_scales};
}

namespace {

struct Binning {
    int tiles_x, tiles_y;
    std::vector<int32_t> rect;  // [N, 4] tile x0, x1, y0, y1 (inclusive), x0 > x1 = no tiles
};

// Inclusive pixel index range [lo, hi] whose centres (j + 0.5) lie within `ext` of `m`.
inline void pixel_range(float m, float ext, int size, int& lo, int& hi) {
    const float e = ext + kBoxSlack;
    lo = std::max(0, static_cast<int>(std::ceil(m - e - 0.5f)));
    hi = std::min(size - 1, static_cast<int>(std::floor(m + e - 0.5f)));
}

// Sortable unsigned key of a float (monotone for all finite values).
inline uint32_t float_key(float f) {
    uint32_t u;
    std::memcpy(&u, &f, sizeof(u));
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

// Stable LSD radix sort of `ids` by `keys[ids]` (11-bit digits, 3 passes).
void radix_sort_by_key(std::vector<int32_t>& ids, const std::vector<uint32_t>& keys) {
    std::vector<int32_t> tmp(ids.size());
    std::vector<uint32_t> k(ids.size()), ktmp(ids.size());
    for (size_t i = 0; i < ids.size(); ++i) k[i] = keys[ids[i]];
    for (int shift = 0; shift < 32; shift += 11) {
        size_t count[2049] = {0};
        for (uint32_t key : k) ++count[((key >> shift) & 2047u) + 1];
        for (int d = 0; d < 2048; ++d) count[d + 1] += count[d];
        for (size_t i = 0; i < ids.size(); ++i) {
            const size_t dst = count[(k[i] >> shift) & 2047u]++;
            tmp[dst] = ids[i];
            ktmp[dst] = k[i];
        }
        ids.swap(tmp);
        k.swap(ktmp);
    }
}

inline void load_rows(float my, float ey, int y0, int height, int& r0, int& r1) {
    int lo, hi;
    pixel_range(my, ey, height, lo, hi);
    r0 = std::max(lo, y0) - y0;
    r1 = std::min(hi, y0 + kTile - 1) - y0;
}

}  // namespace

// Blending forward. Bins visible Gaussians to tiles (front to back), blends every tile and returns
// color [H, W, 3], alpha [H, W, 1], depth_acc [H, W, 1] (sum of w_i z_i) plus what the backward
// needs: final transmittance [H, W], index of the last blended entry per pixel [H, W], tile offsets
// [T + 1], sorted Gaussian ids [I], Gaussian offsets [N + 1] and each Gaussian's entry positions [I].
std::vector<at::Tensor> raster_forward(at::Tensor means2d, at::Tensor conics, at::Tensor colors,
                                          at::Tensor opacities, at::Tensor depths, at::Tensor extents,
                                          at::Tensor radii, int64_t width, int64_t height,
                                          int64_t num_threads) {
    const int64_t N = means2d.size(0);
    const int W = static_cast<int>(width), H = static_cast<int>(height);
    const int tiles_x = (W + kTile - 1) / kTile, tiles_y = (H + kTile - 1) / kTile;
    const int n_tiles = tiles_x * tiles_y;
    const float* pm = means2d.data_ptr<float>();
    const float* pcon = conics.data_ptr<float>();
    const float* pcol = colors.data_ptr<float>();
    const float* po = opacities.data_ptr<float>();
    const float* pz = depths.data_ptr<float>();
    const float* pe = extents.data_ptr<float>();
    const int32_t* prad = radii.data_ptr<int32_t>();

    // ---- binning: tile rectangle per Gaussian, depth order, counting sort into tiles ----
    std::vector<int32_t> rect(4 * N);
    auto gauss_offsets = at::zeros({N + 1}, at::kLong);
    int64_t* goff = gauss_offsets.data_ptr<int64_t>();
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t g = 0; g < N; ++g) {
        int32_t* r = &rect[4 * g];
        r[0] = 0, r[1] = -1, r[2] = 0, r[3] = -1;
        goff[g + 1] = 0;
        if (prad[g] <= 0 || pe[2 * g] < 0.f) continue;
        int j0, j1, i0, i1;
        pixel_range(pm[2 * g], pe[2 * g], W, j0, j1);
        pixel_range(pm[2 * g + 1], pe[2 * g + 1], H, i0, i1);
        if (j0 > j1 || i0 > i1) continue;
        r[0] = j0 / kTile, r[1] = j1 / kTile, r[2] = i0 / kTile, r[3] = i1 / kTile;
        goff[g + 1] = static_cast<int64_t>(r[1] - r[0] + 1) * (r[3] - r[2] + 1);
    }
    for (int64_t g = 0; g < N; ++g) goff[g + 1] += goff[g];
    const int64_t n_isect = goff[N];

    std::vector<int32_t> order;
    std::vector<uint32_t> keys(N);
    order.reserve(N);
    for (int64_t g = 0; g < N; ++g) {
        if (goff[g + 1] > goff[g]) order.push_back(static_cast<int32_t>(g));
        keys[g] = float_key(pz[g]);
    }
    radix_sort_by_key(order, keys);  // stable: equal depths stay in index order

    auto tile_offsets = at::zeros({n_tiles + 1}, at::kLong);
    int64_t* toff = tile_offsets.data_ptr<int64_t>();
    for (int32_t g : order) {
        const int32_t* r = &rect[4 * g];
        for (int ty = r[2]; ty <= r[3]; ++ty)
            for (int tx = r[0]; tx <= r[1]; ++tx) ++toff[ty * tiles_x + tx + 1];
    }
    for (int t = 0; t < n_tiles; ++t) toff[t + 1] += toff[t];
    auto flat_ids = at::empty({n_isect}, at::kInt);
    auto isect_pos = at::empty({n_isect}, at::kLong);
    int32_t* fid = flat_ids.data_ptr<int32_t>();
    int64_t* ipos = isect_pos.data_ptr<int64_t>();
    {
        std::vector<int64_t> cursor(toff, toff + n_tiles);
        for (int32_t g : order) {
            const int32_t* r = &rect[4 * g];
            int64_t k = goff[g];
            for (int ty = r[2]; ty <= r[3]; ++ty)
                for (int tx = r[0]; tx <= r[1]; ++tx) {
                    const int64_t pos = cursor[ty * tiles_x + tx]++;
                    fid[pos] = g;
                    ipos[k++] = pos;
                }
        }
    }

    // ---- blending, one tile per task ----
    auto fopts = means2d.options();
    auto out_color = at::zeros({H, W, 3}, fopts);
    auto out_alpha = at::zeros({H, W, 1}, fopts);
    auto out_depth = at::zeros({H, W, 1}, fopts);
    auto out_T = at::ones({H, W}, fopts);
    auto out_last = at::full({H, W}, -1, at::kInt);
    float* oc = out_color.data_ptr<float>();
    float* oa = out_alpha.data_ptr<float>();
    float* od = out_depth.data_ptr<float>();
    float* oT = out_T.data_ptr<float>();
    int32_t* olast = out_last.data_ptr<int32_t>();

#pragma omp parallel for schedule(dynamic, 1) num_threads(num_threads)
    for (int tile = 0; tile < n_tiles; ++tile) {
        const int x0 = (tile % tiles_x) * kTile, y0 = (tile / tiles_x) * kTile;
        const int rows_in = std::min(kTile, H - y0), cols_in = std::min(kTile, W - x0);
        vf px[kParts] = {};  // pixel-centre x of the 16 columns
        vi col_in[kParts] = {};
        for (int c = 0; c < kTile; ++c) {
            const int p = c / kLanes, l = c % kLanes;
            px[p][l] = static_cast<float>(x0 + c) + 0.5f, col_in[p][l] = c < cols_in ? -1 : 0;
        }
        // per row: transmittance, accumulated colour and depth, last blended entry, still-running mask
        vf T[kTile][kParts], cr[kTile][kParts], cg[kTile][kParts], cb[kTile][kParts], cd[kTile][kParts];
        vi last[kTile][kParts], live[kTile][kParts];
        int n_live = rows_in * cols_in;
        for (int row = 0; row < kTile; ++row) {
            for (int p = 0; p < kParts; ++p) {
                T[row][p] = splat(1.f), cr[row][p] = cg[row][p] = cb[row][p] = cd[row][p] = splat(0.f);
                last[row][p] = splati(-1);
                live[row][p] = row < rows_in ? col_in[p] : splati(0);
            }
        }
        const int64_t s0 = toff[tile], s1 = toff[tile + 1];
        for (int64_t s = s0; s < s1 && n_live > 0; ++s) {
            const int32_t g = fid[s];
            const vi k = splati(static_cast<int32_t>(s - s0));
            const float my = pm[2 * g + 1];
            const float A = pcon[3 * g], B = pcon[3 * g + 1], C = pcon[3 * g + 2];
            const float o = po[g], z = pz[g];
            const float r = pcol[3 * g], gg = pcol[3 * g + 1], b = pcol[3 * g + 2];
            int r0, r1;
            load_rows(my, pe[2 * g + 1], y0, H, r0, r1);
            vi n_term = splati(0);
            for (int p = 0; p < kParts; ++p) {
                const vf dx = pm[2 * g] - px[p];
                const vf Adx2 = A * dx * dx;
                for (int row = r0; row <= r1; ++row) {
                    const float dy = my - (static_cast<float>(y0 + row) + 0.5f);
                    const vf sigma = 0.5f * (Adx2 + C * dy * dy) + B * dx * dy;
                    const vf raw = o * exp_neg(-sigma);
                    const vf alpha = select(raw < kMaxAlpha, raw, splat(kMaxAlpha));
                    const vi hit = live[row][p] & (sigma >= 0.f) & (alpha >= kAlphaThreshold);
                    const vf next_T = T[row][p] * (1.f - alpha);
                    const vi term = hit & (next_T <= kTransmittanceThreshold);
                    const vi blend = hit & ~term;
                    const vf w = select(blend, alpha * T[row][p], splat(0.f));
                    cr[row][p] += w * r;
                    cg[row][p] += w * gg;
                    cb[row][p] += w * b;
                    cd[row][p] += w * z;
                    T[row][p] = select(blend, next_T, T[row][p]);
                    last[row][p] = blend ? k : last[row][p];
                    live[row][p] &= ~term;
                    n_term += term;
                }
            }
            for (int c = 0; c < kLanes; ++c) n_live += n_term[c];  // term lanes are -1
        }
        for (int row = 0; row < rows_in; ++row) {
            for (int c = 0; c < cols_in; ++c) {
                const int64_t pix = static_cast<int64_t>(y0 + row) * W + x0 + c;
                const int p = c / kLanes, l = c % kLanes;
                oc[3 * pix] = cr[row][p][l];
                oc[3 * pix + 1] = cg[row][p][l];
                oc[3 * pix + 2] = cb[row][p][l];
                od[pix] = cd[row][p][l];
                oa[pix] = 1.f - T[row][p][l];
                oT[pix] = T[row][p][l];
                olast[pix] = last[row][p][l];
            }
        }
    }
    return {out_color, out_alpha, out_depth, out_T, out_last, tile_offsets, flat_ids, gauss_offsets, isect_pos};
}

// Blending backward: dL/d(color, alpha, depth_acc) images -> dL/d(means2d, conics, colors,
// opacities, depths). Walks each tile back to front, recovering the transmittance before each
// Gaussian as T / (1 - alpha) from the final one.
std::vector<at::Tensor> raster_backward(at::Tensor means2d, at::Tensor conics, at::Tensor colors,
                                           at::Tensor opacities, at::Tensor depths,
                                           at::Tensor extents, at::Tensor final_T,
                                           at::Tensor last_ids, at::Tensor tile_offsets,
                                           at::Tensor flat_ids, at::Tensor gauss_offsets,
                                           at::Tensor isect_pos, at::Tensor v_color,
                                           at::Tensor v_alpha, at::Tensor v_depth, int64_t width,
                                           int64_t height, int64_t num_threads) {
    const int64_t N = means2d.size(0);
    const int W = static_cast<int>(width), H = static_cast<int>(height);
    const int tiles_x = (W + kTile - 1) / kTile, tiles_y = (H + kTile - 1) / kTile;
    const int n_tiles = tiles_x * tiles_y;
    const int64_t n_isect = flat_ids.size(0);
    const float* pm = means2d.data_ptr<float>();
    const float* pcon = conics.data_ptr<float>();
    const float* pcol = colors.data_ptr<float>();
    const float* po = opacities.data_ptr<float>();
    const float* pz = depths.data_ptr<float>();
    const float* pe = extents.data_ptr<float>();
    const float* pT = final_T.data_ptr<float>();
    const int32_t* plast = last_ids.data_ptr<int32_t>();
    const int64_t* toff = tile_offsets.data_ptr<int64_t>();
    const int32_t* fid = flat_ids.data_ptr<int32_t>();
    const int64_t* goff = gauss_offsets.data_ptr<int64_t>();
    const int64_t* ipos = isect_pos.data_ptr<int64_t>();
    const float* gC = v_color.data_ptr<float>();
    const float* gA = v_alpha.data_ptr<float>();
    const float* gD = v_depth.data_ptr<float>();

    std::vector<float> rows(static_cast<size_t>(n_isect) * kGradStride, 0.f);
    float* buf = rows.data();

#pragma omp parallel for schedule(dynamic, 1) num_threads(num_threads)
    for (int tile = 0; tile < n_tiles; ++tile) {
        const int x0 = (tile % tiles_x) * kTile, y0 = (tile / tiles_x) * kTile;
        const int rows_in = std::min(kTile, H - y0), cols_in = std::min(kTile, W - x0);
        const int64_t s0 = toff[tile];
        vf px[kParts] = {};
        for (int c = 0; c < kTile; ++c) px[c / kLanes][c % kLanes] = static_cast<float>(x0 + c) + 0.5f;
        // per row: transmittance (walking back), colour / depth accumulated behind, output grads
        vf T[kTile][kParts], Sr[kTile][kParts], Sg[kTile][kParts], Sb[kTile][kParts], Sd[kTile][kParts];
        vf gr[kTile][kParts], gg[kTile][kParts], gb[kTile][kParts], gd[kTile][kParts], gaT[kTile][kParts];
        vi last[kTile][kParts];
        int kmax = -1;
        for (int row = 0; row < kTile; ++row) {
            for (int p = 0; p < kParts; ++p) {
                T[row][p] = splat(1.f);
                Sr[row][p] = Sg[row][p] = Sb[row][p] = Sd[row][p] = splat(0.f);
                gr[row][p] = gg[row][p] = gb[row][p] = gd[row][p] = gaT[row][p] = splat(0.f);
                last[row][p] = splati(-1);
            }
            if (row >= rows_in) continue;
            for (int c = 0; c < cols_in; ++c) {
                const int64_t pix = static_cast<int64_t>(y0 + row) * W + x0 + c;
                const int p = c / kLanes, l = c % kLanes;
                T[row][p][l] = pT[pix];
                last[row][p][l] = plast[pix];
                gr[row][p][l] = gC[3 * pix], gg[row][p][l] = gC[3 * pix + 1], gb[row][p][l] = gC[3 * pix + 2];
                gd[row][p][l] = gD[pix];
                // alpha_out = 1 - T_final, and dT_final/dalpha_k = -T_final / (1 - alpha_k)
                gaT[row][p][l] = gA[pix] * pT[pix];
                kmax = std::max(kmax, plast[pix]);
            }
        }
        for (int kk = kmax; kk >= 0; --kk) {
            const int64_t s = s0 + kk;
            const int32_t g = fid[s];
            const vi k = splati(kk);
            const float my = pm[2 * g + 1];
            const float A = pcon[3 * g], B = pcon[3 * g + 1], C = pcon[3 * g + 2];
            const float o = po[g], z = pz[g];
            const float r = pcol[3 * g], gcol = pcol[3 * g + 1], b = pcol[3 * g + 2];
            int r0, r1;
            load_rows(my, pe[2 * g + 1], y0, H, r0, r1);
            const vf zero = splat(0.f);
            float* out = buf + s * kGradStride;  // (zeros: each sum runs over the lanes in order)
            for (int p = 0; p < kParts; ++p) {
                const vf dx = pm[2 * g] - px[p];
                const vf Adx2 = A * dx * dx;
                vf v_mx = zero, v_my = zero, vA = zero, vB = zero, vC = zero;
                vf v_r = zero, v_g = zero, v_b = zero, v_o = zero, v_z = zero;
                for (int row = r0; row <= r1; ++row) {
                    const float dy = my - (static_cast<float>(y0 + row) + 0.5f);
                    const vf sigma = 0.5f * (Adx2 + C * dy * dy) + B * dx * dy;
                    const vf G = exp_neg(-sigma);
                    const vf raw = o * G;
                    const vf alpha = select(raw < kMaxAlpha, raw, splat(kMaxAlpha));
                    const vi hit = (k <= last[row][p]) & (sigma >= 0.f) & (alpha >= kAlphaThreshold);
                    const vf ra = 1.f / (1.f - alpha);
                    const vf Tk = T[row][p] * ra;  // transmittance in front of this Gaussian
                    const vf w = select(hit, alpha * Tk, zero);
                    const vf front = r * gr[row][p] + gcol * gg[row][p] + b * gb[row][p] + z * gd[row][p];
                    const vf behind = Sr[row][p] * gr[row][p] + Sg[row][p] * gg[row][p] +
                                      Sb[row][p] * gb[row][p] + Sd[row][p] * gd[row][p];
                    const vf v_alpha = Tk * front - behind * ra + gaT[row][p] * ra;
                    // min(0.99, raw) passes no gradient where it clamps
                    const vi grad_ok = hit & (raw <= kMaxAlpha);
                    const vf v_raw = select(grad_ok, v_alpha, zero);
                    const vf v_sigma = -raw * v_raw;
                    v_r += w * gr[row][p];
                    v_g += w * gg[row][p];
                    v_b += w * gb[row][p];
                    v_z += w * gd[row][p];
                    v_o += G * v_raw;
                    v_mx += v_sigma * (A * dx + B * dy);
                    v_my += v_sigma * (B * dx + C * dy);
                    vA += 0.5f * v_sigma * dx * dx;
                    vB += v_sigma * dx * dy;
                    vC += 0.5f * v_sigma * dy * dy;
                    Sr[row][p] += w * r;
                    Sg[row][p] += w * gcol;
                    Sb[row][p] += w * b;
                    Sd[row][p] += w * z;
                    T[row][p] = select(hit, Tk, T[row][p]);
                }
                out[0] = hsum(out[0], v_mx), out[1] = hsum(out[1], v_my), out[2] = hsum(out[2], vA);
                out[3] = hsum(out[3], vB), out[4] = hsum(out[4], vC), out[5] = hsum(out[5], v_r);
                out[6] = hsum(out[6], v_g), out[7] = hsum(out[7], v_b), out[8] = hsum(out[8], v_o);
                out[9] = hsum(out[9], v_z);
            }
        }
    }

    // Per-Gaussian sums over its intersections, in tile order: deterministic for any thread count.
    auto opts = means2d.options();
    auto v_means2d = at::zeros({N, 2}, opts);
    auto v_conics = at::zeros({N, 3}, opts);
    auto v_colors = at::zeros({N, 3}, opts);
    auto v_opac = at::zeros({N}, opts);
    auto v_depths = at::zeros({N}, opts);
    float* om = v_means2d.data_ptr<float>();
    float* oc = v_conics.data_ptr<float>();
    float* ocol = v_colors.data_ptr<float>();
    float* oo = v_opac.data_ptr<float>();
    float* oz = v_depths.data_ptr<float>();
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t g = 0; g < N; ++g) {
        float acc[kGradStride] = {0.f};
        for (int64_t k = goff[g]; k < goff[g + 1]; ++k) {
            const float* row = buf + ipos[k] * kGradStride;
            for (int i = 0; i < kGradStride; ++i) acc[i] += row[i];
        }
        om[2 * g] = acc[0], om[2 * g + 1] = acc[1];
        oc[3 * g] = acc[2], oc[3 * g + 1] = acc[3], oc[3 * g + 2] = acc[4];
        ocol[3 * g] = acc[5], ocol[3 * g + 1] = acc[6], ocol[3 * g + 2] = acc[7];
        oo[g] = acc[8];
        oz[g] = acc[9];
    }
    return {v_means2d, v_conics, v_colors, v_opac, v_depths};
}

// ----- View-dependent colour: spherical harmonics (render/sh.py's eval_sh_colors) ------------------
// One Gaussian's colour max(SH(d) . coeffs + 0.5, 0), d the unit direction from the camera centre to
// its mean, and its backward, recomputed rather than stored. As ATen ops this was ~20 small ops and
// ~14 autograd nodes on [N, K, 3] tensors (about 1.1 ms a step at 7k Gaussians, degree 1); here it
// is one pass over the Gaussians each way.
namespace {

constexpr float kSHC0 = 0.28209479177387814f;
constexpr float kSHC1 = 0.4886025119029199f;
constexpr float kSHC2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f,
                            -1.0925484305920792f, 0.5462742152960396f};
constexpr float kSHC3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f,
                            0.3731763325901154f,  -0.4570457994644658f, 1.445305721320277f,
                            -0.5900435899266435f};

// The real SH basis up to ``degree`` (0..3) at the unit direction (x, y, z), 3DGS's order.
inline void sh_basis(int degree, float x, float y, float z, float b[16]) {
    b[0] = kSHC0;
    if (degree < 1) return;
    b[1] = -kSHC1 * y;
    b[2] = kSHC1 * z;
    b[3] = -kSHC1 * x;
    if (degree < 2) return;
    const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    b[4] = kSHC2[0] * xy;
    b[5] = kSHC2[1] * yz;
    b[6] = kSHC2[2] * (2.f * zz - xx - yy);
    b[7] = kSHC2[3] * xz;
    b[8] = kSHC2[4] * (xx - yy);
    if (degree < 3) return;
    b[9] = kSHC3[0] * y * (3.f * xx - yy);
    b[10] = kSHC3[1] * xy * z;
    b[11] = kSHC3[2] * y * (4.f * zz - xx - yy);
    b[12] = kSHC3[3] * z * (2.f * zz - 3.f * xx - 3.f * yy);
    b[13] = kSHC3[4] * x * (4.f * zz - xx - yy);
    b[14] = kSHC3[5] * z * (xx - yy);
    b[15] = kSHC3[6] * x * (xx - 3.f * yy);
}

// dL/d(x, y, z) of the basis's values from dL/d(basis) ``vb`` (x, y, z taken as independent).
inline void sh_basis_vjp(int degree, float x, float y, float z, const float vb[16], float v[3]) {
    v[0] = v[1] = v[2] = 0.f;
    if (degree < 1) return;
    v[0] += -kSHC1 * vb[3];
    v[1] += -kSHC1 * vb[1];
    v[2] += kSHC1 * vb[2];
    if (degree < 2) return;
    const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    v[0] += kSHC2[0] * y * vb[4] - 2.f * kSHC2[2] * x * vb[6] + kSHC2[3] * z * vb[7] + 2.f * kSHC2[4] * x * vb[8];
    v[1] += kSHC2[0] * x * vb[4] + kSHC2[1] * z * vb[5] - 2.f * kSHC2[2] * y * vb[6] - 2.f * kSHC2[4] * y * vb[8];
    v[2] += kSHC2[1] * y * vb[5] + 4.f * kSHC2[2] * z * vb[6] + kSHC2[3] * x * vb[7];
    if (degree < 3) return;
    v[0] += kSHC3[0] * 6.f * xy * vb[9] + kSHC3[1] * yz * vb[10] - kSHC3[2] * 2.f * xy * vb[11] -
            kSHC3[3] * 6.f * xz * vb[12] + kSHC3[4] * (4.f * zz - 3.f * xx - yy) * vb[13] +
            kSHC3[5] * 2.f * xz * vb[14] + kSHC3[6] * 3.f * (xx - yy) * vb[15];
    v[1] += kSHC3[0] * 3.f * (xx - yy) * vb[9] + kSHC3[1] * xz * vb[10] +
            kSHC3[2] * (4.f * zz - xx - 3.f * yy) * vb[11] - kSHC3[3] * 6.f * yz * vb[12] -
            kSHC3[4] * 2.f * xy * vb[13] - kSHC3[5] * 2.f * yz * vb[14] - kSHC3[6] * 6.f * xy * vb[15];
    v[2] += kSHC3[1] * xy * vb[10] + kSHC3[2] * 8.f * yz * vb[11] +
            kSHC3[3] * (6.f * zz - 3.f * xx - 3.f * yy) * vb[12] + kSHC3[4] * 8.f * xz * vb[13] +
            kSHC3[5] * (xx - yy) * vb[14];
}

// The camera centre -R^T t of a world-to-camera matrix.
inline void camera_centre(const at::Tensor& viewmat, float c[3]) {
    auto v = viewmat.accessor<float, 2>();
    for (int j = 0; j < 3; ++j) c[j] = -(v[0][j] * v[0][3] + v[1][j] * v[1][3] + v[2][j] * v[2][3]);
}

// The unit direction from ``centre`` to ``mean`` and 1 / its clamped length (as torch's
// d / d.norm().clamp_min(1e-12)); ``clamped``: the length was below the clamp.
inline void sh_direction(const float* mean, const float centre[3], float n[3], float& inv, bool& clamped) {
    const float d0 = mean[0] - centre[0], d1 = mean[1] - centre[1], d2 = mean[2] - centre[2];
    const float len = std::sqrt(d0 * d0 + d1 * d1 + d2 * d2);
    clamped = !(len >= 1e-12f);
    inv = 1.f / (clamped ? 1e-12f : len);
    n[0] = d0 * inv;
    n[1] = d1 * inv;
    n[2] = d2 * inv;
}

// One Gaussian's SH sum + 0.5 per channel (before the clamp at 0) into ``rgb``, with what the backward
// reuses: its unit direction ``n``, 1 / the clamped length, whether it was clamped, and the basis ``b``.
inline void sh_colour(int degree, const float* mean, const float centre[3], const float* c, float rgb[3],
                      float n[3], float& inv, bool& clamped, float b[16]) {
    sh_direction(mean, centre, n, inv, clamped);
    sh_basis(degree, n[0], n[1], n[2], b);
    const int nb = (degree + 1) * (degree + 1);
    for (int ch = 0; ch < 3; ++ch) {
        float sum = 0.f;
        for (int k = 0; k < nb; ++k) sum += b[k] * c[3 * k + ch];
        rgb[ch] = sum + 0.5f;
    }
}

}  // namespace

// Colours [N, 3] of Gaussians ``means`` [N, 3] with SH coefficients ``coeffs`` [N, K, 3] (K >=
// (degree + 1)^2) seen from the camera of ``viewmat``.
at::Tensor sh_forward(at::Tensor means, at::Tensor coeffs, at::Tensor viewmat, int64_t degree,
                      int64_t num_threads) {
    const int64_t N = means.size(0), K = coeffs.size(1);
    float centre[3];
    camera_centre(viewmat, centre);
    auto colors = at::empty({N, 3}, means.options());
    const float* pm = means.data_ptr<float>();
    const float* pc = coeffs.data_ptr<float>();
    float* out = colors.data_ptr<float>();
    const int deg = static_cast<int>(degree);
#pragma omp parallel for schedule(static) num_threads(num_threads) if (N > 4096)
    for (int64_t g = 0; g < N; ++g) {
        float rgb[3], n[3], inv, b[16];
        bool clamped;
        sh_colour(deg, pm + 3 * g, centre, pc + g * K * 3, rgb, n, inv, clamped, b);
        for (int ch = 0; ch < 3; ++ch) out[3 * g + ch] = std::max(rgb[ch], 0.f);
    }
    return colors;
}

// dL/d(means) [N, 3] and dL/d(coeffs) [N, K, 3] (zero beyond the degree's coefficients) from
// dL/d(colours) ``v_colors`` [N, 3]; the clamp at 0 passes the gradient where SH + 0.5 >= 0 (torch's
// clamp_min).
std::vector<at::Tensor> sh_backward(at::Tensor means, at::Tensor coeffs, at::Tensor viewmat,
                                    int64_t degree, at::Tensor v_colors, int64_t num_threads) {
    const int64_t N = means.size(0), K = coeffs.size(1);
    const int nb = static_cast<int>((degree + 1) * (degree + 1));
    float centre[3];
    camera_centre(viewmat, centre);
    auto v_means = at::empty({N, 3}, means.options());
    auto v_coeffs = at::empty({N, K, 3}, coeffs.options());
    const float* pm = means.data_ptr<float>();
    const float* pc = coeffs.data_ptr<float>();
    const float* gv = v_colors.data_ptr<float>();
    float* vm = v_means.data_ptr<float>();
    float* vc = v_coeffs.data_ptr<float>();
    const int deg = static_cast<int>(degree);
#pragma omp parallel for schedule(static) num_threads(num_threads) if (N > 4096)
    for (int64_t g = 0; g < N; ++g) {
        float rgb[3], n[3], inv, b[16], vb[16], vrgb[3];
        bool clamped;
        const float* c = pc + g * K * 3;
        sh_colour(deg, pm + 3 * g, centre, c, rgb, n, inv, clamped, b);
        for (int ch = 0; ch < 3; ++ch) vrgb[ch] = rgb[ch] >= 0.f ? gv[3 * g + ch] : 0.f;
        float* o = vc + g * K * 3;
        for (int k = 0; k < nb; ++k) {
            vb[k] = c[3 * k] * vrgb[0] + c[3 * k + 1] * vrgb[1] + c[3 * k + 2] * vrgb[2];
            for (int ch = 0; ch < 3; ++ch) o[3 * k + ch] = b[k] * vrgb[ch];
        }
        for (int64_t k = nb; k < K; ++k) o[3 * k] = o[3 * k + 1] = o[3 * k + 2] = 0.f;
        float vn[3];
        sh_basis_vjp(deg, n[0], n[1], n[2], vb, vn);
        // through n = d * inv: (vn - n (n . vn)) * inv, or vn * inv where the length was clamped
        const float along = clamped ? 0.f : n[0] * vn[0] + n[1] * vn[1] + n[2] * vn[2];
        for (int i = 0; i < 3; ++i) vm[3 * g + i] = (vn[i] - n[i] * along) * inv;
    }
    return {v_means, v_coeffs};
}

bool has_openmp() {
#ifdef _OPENMP
    return true;
#else
    return false;
#endif
}

// Registered as operators (torch.ops.tracegs_raster_cpu.*), not a pybind11 module: the build then needs
// ATen's headers only, not torch/extension.h's (about 5 s of compiling instead of 18). The kernels
// touch no Python objects, and torch.ops calls release the GIL.
TORCH_LIBRARY(tracegs_raster_cpu, m) {
    m.def("project_forward", &project_forward);
    m.def("project_backward", &project_backward);
    m.def("raster_forward", &raster_forward);
    m.def("raster_backward", &raster_backward);
    m.def("sh_forward", &sh_forward);
    m.def("sh_backward", &sh_backward);
    m.def("has_openmp", &has_openmp);
}
