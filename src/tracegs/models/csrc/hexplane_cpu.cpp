// CPU kernels of the HexPlane grid (the TRACE_4dgs deformation field's encoder): bilinear sampling
// of P channels-last planes and the product of the samples, its backward, and a plane's total
// variation with its gradient. torch's grid_sample runs its CPU backward on one thread over a
// channels-first plane; here each plane's gradient is scattered by one thread over rows of C
// contiguous floats, which is several times faster on two cores (docs/DESIGN.md, "TRACE_4dgs").
//
// N: points, P: planes, C: channels, a plane is a table [H, W, C] (row-major, channels last).
// Sampling follows grid_sample(mode="bilinear", padding_mode="border", align_corners=True): the
// coordinate u in [-1, 1] maps to (u + 1) / 2 * (W - 1), clamped to the border, and the gradient
// with respect to a coordinate on or beyond the border is zero. Every sum runs in an order that does
// not depend on the thread count.

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/scalar_tensor.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

struct Axis {
    int64_t i0, i1;  // the two cells
    float f;         // weight of i1
    float dscale;    // d position / d u, 0 on or beyond the border
};

inline Axis locate(float u, int64_t n) {
    const float last = float(n - 1);
    float p = (u + 1.0f) * 0.5f * last;
    Axis a;
    a.dscale = (p > 0.0f && p < last) ? 0.5f * last : 0.0f;
    p = std::min(std::max(p, 0.0f), last);
    a.i0 = std::min<int64_t>(int64_t(std::floor(p)), std::max<int64_t>(n - 2, 0));
    a.i1 = std::min<int64_t>(a.i0 + 1, n - 1);
    a.f = p - float(a.i0);
    return a;
}

struct Planes {
    std::vector<const float*> data;
    std::vector<int64_t> H, W, ax, ay;  // ax: coordinate read along W, ay: along H
    int64_t P = 0, C = 0;
};

Planes check_planes(at::TensorList tables, at::IntArrayRef axes) {
    Planes pl;
    pl.P = int64_t(tables.size());
    TORCH_CHECK(pl.P > 0 && int64_t(axes.size()) == 2 * pl.P, "hexplane: need two axes per plane");
    pl.C = tables[0].size(2);
    for (const auto& t : tables) {
        TORCH_CHECK(t.dim() == 3 && t.size(2) == pl.C, "hexplane: planes must be [H, W, C] with one C");
        TORCH_CHECK(t.scalar_type() == at::kFloat && t.is_contiguous(), "hexplane: float32 contiguous planes");
        pl.data.push_back(t.data_ptr<float>());
        pl.H.push_back(t.size(0));
        pl.W.push_back(t.size(1));
    }
    for (int64_t p = 0; p < pl.P; ++p) pl.ax.push_back(axes[2 * p]), pl.ay.push_back(axes[2 * p + 1]);
    return pl;
}

// features [N, C] = prod_p bilinear(plane_p, coords[:, ax_p], coords[:, ay_p]); samples [P, N, C]
std::vector<at::Tensor> hexplane_forward(
    at::TensorList tables, const at::Tensor& coords, at::IntArrayRef axes, int64_t num_threads) {
    const Planes pl = check_planes(tables, axes);
    TORCH_CHECK(coords.scalar_type() == at::kFloat && coords.is_contiguous() && coords.dim() == 2,
                "hexplane: coords must be float32 contiguous [N, D]");
    const int64_t N = coords.size(0), D = coords.size(1), P = pl.P, C = pl.C;
    auto out = at::empty({N, C}, coords.options());
    auto samples = at::empty({P, N, C}, coords.options());
    const float* u = coords.data_ptr<float>();
    float* o = out.data_ptr<float>();
    float* s = samples.data_ptr<float>();
#pragma omp parallel for num_threads(num_threads) schedule(static)
    for (int64_t n = 0; n < N; ++n) {
        float* on = o + n * C;
        for (int64_t c = 0; c < C; ++c) on[c] = 1.0f;
        for (int64_t p = 0; p < P; ++p) {
            const Axis x = locate(u[n * D + pl.ax[p]], pl.W[p]);
            const Axis y = locate(u[n * D + pl.ay[p]], pl.H[p]);
            const int64_t W = pl.W[p];
            const float* a = pl.data[p] + (y.i0 * W + x.i0) * C;
            const float* b = pl.data[p] + (y.i0 * W + x.i1) * C;
            const float* c0 = pl.data[p] + (y.i1 * W + x.i0) * C;
            const float* d = pl.data[p] + (y.i1 * W + x.i1) * C;
            const float wa = (1 - x.f) * (1 - y.f), wb = x.f * (1 - y.f), wc = (1 - x.f) * y.f, wd = x.f * y.f;
            float* sn = s + (p * N + n) * C;
            for (int64_t c = 0; c < C; ++c) {
                sn[c] = wa * a[c] + wb * b[c] + wc * c0[c] + wd * d[c];
                on[c] *= sn[c];
            }
        }
    }
    return {out, samples};
}

// Gradients of sum(grad_out * features) with respect to every table and (if asked) the coords.
// One thread per plane scatters that plane's gradient over all points: no two threads write the
// same table, and each table's sums run in point order.
std::vector<at::Tensor> hexplane_backward(at::TensorList tables, const at::Tensor& coords,
                                          at::IntArrayRef axes, const at::Tensor& samples,
                                          const at::Tensor& grad_out, bool coords_grad, int64_t num_threads) {
    const Planes pl = check_planes(tables, axes);
    const int64_t N = coords.size(0), D = coords.size(1), P = pl.P, C = pl.C;
    TORCH_CHECK(grad_out.is_contiguous() && samples.is_contiguous(), "hexplane: contiguous gradients");
    std::vector<at::Tensor> grads;
    std::vector<float*> gp;
    for (const auto& t : tables) {
        grads.push_back(at::zeros_like(t));
        gp.push_back(grads.back().data_ptr<float>());
    }
    // per-plane coordinate gradients [P, N, 2], summed over planes afterwards in plane order
    auto part = coords_grad ? at::zeros({P, N, 2}, coords.options()) : at::Tensor();
    float* pg = coords_grad ? part.data_ptr<float>() : nullptr;
    const float* u = coords.data_ptr<float>();
    const float* s = samples.data_ptr<float>();
    const float* g = grad_out.data_ptr<float>();
#pragma omp parallel for num_threads(num_threads) schedule(dynamic, 1)
    for (int64_t p = 0; p < P; ++p) {
        std::vector<float> gk(C);
        const int64_t W = pl.W[p];
        const float* tab = pl.data[p];
        float* gt = gp[p];
        for (int64_t n = 0; n < N; ++n) {
            // d features / d sample_p = product of the other planes' samples
            for (int64_t c = 0; c < C; ++c) gk[c] = g[n * C + c];
            for (int64_t q = 0; q < P; ++q) {
                if (q == p) continue;
                const float* sq = s + (q * N + n) * C;
                for (int64_t c = 0; c < C; ++c) gk[c] *= sq[c];
            }
            const Axis x = locate(u[n * D + pl.ax[p]], W);
            const Axis y = locate(u[n * D + pl.ay[p]], pl.H[p]);
            const int64_t ia = (y.i0 * W + x.i0) * C, ib = (y.i0 * W + x.i1) * C;
            const int64_t ic = (y.i1 * W + x.i0) * C, id = (y.i1 * W + x.i1) * C;
            const float wa = (1 - x.f) * (1 - y.f), wb = x.f * (1 - y.f), wc = (1 - x.f) * y.f, wd = x.f * y.f;
            for (int64_t c = 0; c < C; ++c) {
                gt[ia + c] += wa * gk[c];
                gt[ib + c] += wb * gk[c];
                gt[ic + c] += wc * gk[c];
                gt[id + c] += wd * gk[c];
            }
            if (pg != nullptr) {
                float gx = 0.0f, gy = 0.0f;
                for (int64_t c = 0; c < C; ++c) {
                    const float va = tab[ia + c], vb = tab[ib + c], vc = tab[ic + c], vd = tab[id + c];
                    gx += gk[c] * ((vb - va) * (1 - y.f) + (vd - vc) * y.f);
                    gy += gk[c] * ((vc - va) * (1 - x.f) + (vd - vb) * x.f);
                }
                pg[(p * N + n) * 2] = gx * x.dscale;
                pg[(p * N + n) * 2 + 1] = gy * y.dscale;
            }
        }
    }
    if (coords_grad) {
        auto gc = at::zeros_like(coords);
        float* gcp = gc.data_ptr<float>();
#pragma omp parallel for num_threads(num_threads) schedule(static)
        for (int64_t n = 0; n < N; ++n)
            for (int64_t p = 0; p < P; ++p) {
                gcp[n * D + pl.ax[p]] += pg[(p * N + n) * 2];
                gcp[n * D + pl.ay[p]] += pg[(p * N + n) * 2 + 1];
            }
        grads.push_back(gc);
    }
    return grads;
}

// Sum of squares of a[k] - b[k], k < n, in 8 float lanes (vectorisable without fast-math), in double.
inline double sum_sq_diff(const float* a, const float* b, int64_t n) {
    float lane[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    int64_t k = 0;
    for (; k + 8 <= n; k += 8)
        for (int l = 0; l < 8; ++l) {
            const float d = a[k + l] - b[k + l];
            lane[l] += d * d;
        }
    double total = 0.0;
    for (; k < n; ++k) total += double(a[k] - b[k]) * double(a[k] - b[k]);
    for (int l = 0; l < 8; ++l) total += lane[l];
    return total;
}

// scale x total variation of a table [H, W, C]: 2 (mean of squared steps along H + mean along W), as
// models/hexplane.py's plane_tv_reference on [1, C, H, W]; returns (loss, d loss / d table).
std::vector<at::Tensor> plane_tv(at::Tensor table, double scale, int64_t num_threads) {
    TORCH_CHECK(table.dim() == 3 && table.scalar_type() == at::kFloat && table.is_contiguous(),
                "plane_tv: float32 contiguous [H, W, C]");
    const int64_t H = table.size(0), W = table.size(1), C = table.size(2), rs = W * C;
    const double nh = double(H - 1) * rs, nw = double(H) * (W - 1) * C;
    const float kh = nh > 0 ? float(4.0 * scale / nh) : 0.0f, kw = nw > 0 ? float(4.0 * scale / nw) : 0.0f;
    auto grad = at::zeros_like(table);
    const float* t = table.data_ptr<float>();
    float* gr = grad.data_ptr<float>();
    std::vector<double> row_h(H, 0.0), row_w(H, 0.0);  // per-row sums, added in row order below
#pragma omp parallel for num_threads(num_threads) schedule(static)
    for (int64_t y = 0; y < H; ++y) {
        const float* row = t + y * rs;
        float* g = gr + y * rs;
        if (y + 1 < H) {  // step to the next row
            row_h[y] = sum_sq_diff(row + rs, row, rs);
            for (int64_t k = 0; k < rs; ++k) g[k] -= kh * (row[k + rs] - row[k]);
        }
        if (y > 0)  // step from the previous row
            for (int64_t k = 0; k < rs; ++k) g[k] += kh * (row[k] - row[k - rs]);
        if (W > 1) {  // steps along the row
            row_w[y] = sum_sq_diff(row + C, row, rs - C);
            for (int64_t k = 0; k < rs - C; ++k) g[k] -= kw * (row[k + C] - row[k]);
            for (int64_t k = C; k < rs; ++k) g[k] += kw * (row[k] - row[k - C]);
        }
    }
    double sh = 0.0, sw = 0.0;
    for (int64_t y = 0; y < H; ++y) sh += row_h[y], sw += row_w[y];
    const double loss = 2.0 * scale * ((nh > 0 ? sh / nh : 0.0) + (nw > 0 ? sw / nw : 0.0));
    return {at::scalar_tensor(float(loss), table.options()), grad};
}

}  // namespace

// Registered as operators (torch.ops.tracegs_hexplane_cpu.*), not a pybind11 module: the build then needs
// ATen's headers only, not torch/extension.h's (about 5 s of compiling instead of 18). The kernels
// touch no Python objects, and torch.ops calls release the GIL.
TORCH_LIBRARY(tracegs_hexplane_cpu, m) {
    m.def("hexplane_forward", &hexplane_forward);
    m.def("hexplane_backward", &hexplane_backward);
    m.def("plane_tv", &plane_tv);
}
