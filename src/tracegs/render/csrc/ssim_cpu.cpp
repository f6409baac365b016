// SSIM of the training loss with its explicit backward, on the CPU: 11-tap Gaussian window (sigma
// 1.5) applied separably with "valid" filtering, K1 = 0.01, K2 = 0.03, data range 1; the SSIM map
// averaged over pixels and channels (pytorch-msssim's ssim(size_average=True), which
// tracegs.image_metrics.ssim calls). The gradient is taken with respect to the rendered image only.
//
// H x W: image, C = 3 channels, K = 11 taps, Ho x Wo = (H - K + 1) x (W - K + 1).
// With the moments m1 = g * x, m2 = g * x^2, m12 = g * (x y) (my, myy the target's), the SSIM map is
// S = A1 A2 / (B1 B2), A1 = 2 m1 my + C1, A2 = 2 (m12 - m1 my) + C2, B1 = m1^2 + my^2 + C1,
// B2 = m2 - m1^2 + myy - my^2 + C2; dS/dx(q) = sum_p g(p - q) [dS/dm1 + 2 x(q) dS/dm2 + y(q) dS/dm12](p),
// i.e. the three partial maps filtered by the transposed ("full") window. The forward keeps them.
// The filterings run as parallel tasks (15 forward: 3 channels x 5 moments; 9 backward), the map
// by fixed blocks of rows; each channel's mean is summed over those blocks in a fixed order, so the
// result does not depend on the thread count.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/full.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <memory>
#include <vector>

namespace {

constexpr int kTaps = 11;
constexpr float kSigma = 1.5f;
constexpr float kC1 = 0.01f * 0.01f;
constexpr float kC2 = 0.03f * 0.03f;

std::vector<float> window() {
    std::vector<float> g(kTaps);
    float sum = 0.0f;
    for (int k = 0; k < kTaps; ++k) {
        const float c = static_cast<float>(k - kTaps / 2);
        g[k] = std::exp(-(c * c) / (2.0f * kSigma * kSigma));
        sum += g[k];
    }
    for (float& v : g) v /= sum;
    return g;
}

// [h, w] -> [h - K + 1, w - K + 1]: the window along rows, then along columns ("valid"). Each output
// is one sum over the taps in registers, the loop over outputs vectorised (a sum kept in memory
// across the taps was 2 stores and 2 loads a tap); the taps are added in order, from zero.
void filter_valid(const float* __restrict__ in, float* __restrict__ tmp, float* __restrict__ out, int h, int w,
                  const float* __restrict__ g) {
    const int wo = w - kTaps + 1, ho = h - kTaps + 1;
    float gk[kTaps];
    for (int k = 0; k < kTaps; ++k) gk[k] = g[k];
    for (int i = 0; i < h; ++i) {
        float* __restrict__ t = tmp + i * wo;
        const float* __restrict__ r = in + i * w;
        for (int j = 0; j < wo; ++j) {
            float sum = 0.0f;
            for (int k = 0; k < kTaps; ++k) sum += gk[k] * r[j + k];
            t[j] = sum;
        }
    }
    for (int i = 0; i < ho; ++i) {
        float* __restrict__ o = out + i * wo;
        const float* __restrict__ t = tmp + i * wo;
        for (int j = 0; j < wo; ++j) {
            float sum = 0.0f;
            for (int k = 0; k < kTaps; ++k) sum += gk[k] * t[k * wo + j];
            o[j] = sum;
        }
    }
}

// The SSIM map over elements [i0, i1) from the moments, and its partials (see the top).
void ssim_map(const float* __restrict__ m1, const float* __restrict__ my, const float* __restrict__ m2,
              const float* __restrict__ myy, const float* __restrict__ m12, float* __restrict__ d1,
              float* __restrict__ d2, float* __restrict__ d12, float* __restrict__ sm, int i0, int i1) {
    for (int i = i0; i < i1; ++i) {
        const float mx = m1[i], mu = my[i];
        const float a1 = 2.0f * mx * mu + kC1, a2 = 2.0f * (m12[i] - mx * mu) + kC2;
        const float b1 = mx * mx + mu * mu + kC1, b2 = (m2[i] - mx * mx) + (myy[i] - mu * mu) + kC2;
        const float s = (a1 * a2) / (b1 * b2);
        sm[i] = s;
        d1[i] = s * (2.0f * mu / a1 - 2.0f * mu / a2 - 2.0f * mx / b1 + 2.0f * mx / b2);
        d2[i] = -s / b2;
        d12[i] = s * 2.0f / a2;
    }
}

typedef float floatx16 __attribute__((vector_size(64)));

inline floatx16 load16(const float* p) {
    floatx16 v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}

// The transpose of filter_valid: [h - K + 1, w - K + 1] -> [h, w] ("full"), as sums gathered per
// output in registers, their terms in the order the scattered form adds them (the same result). The
// column pass reads rows of tmp padded with K - 1 zeros on each side (zero terms change no sum).
void filter_full(const float* __restrict__ in, float* __restrict__ tmp, float* __restrict__ out, int h, int w,
                 const float* __restrict__ g) {
    const int wo = w - kTaps + 1, ho = h - kTaps + 1, pad = kTaps - 1, wp = wo + 2 * pad;
    float gk[kTaps];
    for (int k = 0; k < kTaps; ++k) gk[k] = g[k];
    // along columns: tmp[r] = the sum over input rows i = r - k in range, i ascending, of g[r - i] in[i]
    for (int r = 0; r < h; ++r) {
        const int i_lo = std::max(0, r - kTaps + 1), i_hi = std::min(ho - 1, r);
        float* __restrict__ t = tmp + r * wp;
        for (int j = 0; j < pad; ++j) t[j] = t[pad + wo + j] = 0.0f;
        int j = 0;
        for (; j + 16 <= wo; j += 16) {  // (16 columns at a time: the compiler keeps the row loop scalar)
            floatx16 sum = {};
            for (int i = i_lo; i <= i_hi; ++i) sum += gk[r - i] * load16(in + i * wo + j);
            std::memcpy(t + pad + j, &sum, sizeof(sum));
        }
        for (; j < wo; ++j) {
            float sum = 0.0f;
            for (int i = i_lo; i <= i_hi; ++i) sum += gk[r - i] * in[i * wo + j];
            t[pad + j] = sum;
        }
    }
    // along rows: out[q] = the sum over the taps k ascending of g[k] tmp[q - k] (zero outside)
    for (int i = 0; i < h; ++i) {
        float* __restrict__ o = out + i * w;
        const float* __restrict__ t = tmp + i * wp + pad;
        for (int q = 0; q < w; ++q) {
            float sum = 0.0f;
            for (int k = 0; k < kTaps; ++k) sum += gk[k] * t[q - k];
            o[q] = sum;
        }
    }
}

void check_images(const at::Tensor& img, const at::Tensor& ref) {
    TORCH_CHECK(img.dim() == 3 && img.size(2) == 3, "ssim: images must be [H, W, 3]");
    TORCH_CHECK(img.sizes() == ref.sizes(), "ssim: the two images differ in size");
    TORCH_CHECK(img.scalar_type() == at::kFloat && ref.scalar_type() == at::kFloat,
                "ssim: float32 images expected");
    TORCH_CHECK(img.size(0) >= kTaps && img.size(1) >= kTaps, "ssim: images smaller than the window");
}

// Channel c of a contiguous [H, W, 3] image as a plane [H, W].
void plane(const float* hwc, int c, int n, float* out) {
    for (int i = 0; i < n; ++i) out[i] = hwc[3 * i + c];
}

}  // namespace

// (mean SSIM [], partial maps [3 channels, 3 maps, Ho, Wo]) of img against ref, both [H, W, 3].
std::vector<at::Tensor> ssim_forward(at::Tensor img, at::Tensor ref) {
    check_images(img, ref);
    img = img.contiguous();
    ref = ref.contiguous();
    const int h = img.size(0), w = img.size(1), ho = h - kTaps + 1, wo = w - kTaps + 1, n = h * w, m = ho * wo;
    const std::vector<float> g = window();
    auto partials = at::empty({3, 3, ho, wo}, img.options());
    const float* x_hwc = img.data_ptr<float>();
    const float* y_hwc = ref.data_ptr<float>();
    float* p = partials.data_ptr<float>();
    // the moments [channel][m1, my, m2, myy, m12][Ho * Wo]
    const std::unique_ptr<float[]> moments(new float[3 * 5 * m]);  // (every element written before read)
    at::parallel_for(0, 15, 1, [&](int64_t j0, int64_t j1) {
        const std::unique_ptr<float[]> x(new float[n]), y(new float[n]), tmp(new float[h * wo]);
        for (int64_t j = j0; j < j1; ++j) {
            const int c = int(j / 5), moment = int(j % 5);
            plane(moment == 1 || moment == 3 ? y_hwc : x_hwc, c, n, x.get());
            if (moment == 2 || moment == 3) {
                for (int i = 0; i < n; ++i) x[i] = x[i] * x[i];
            } else if (moment == 4) {
                plane(y_hwc, c, n, y.get());
                for (int i = 0; i < n; ++i) x[i] = x[i] * y[i];
            }
            filter_valid(x.get(), tmp.get(), moments.get() + j * m, h, w, g.data());
        }
    });
    // the SSIM map and its partials by fixed blocks of rows (tasks of equal size for any thread count),
    // in a function of their own with the map in a buffer, so that the element-wise loop vectorises
    // (a double sum in the same loop, or a lambda's pointers, keep it scalar); each block's sum in
    // double, the blocks' sums added in order.
    constexpr int kBlocks = 8;  // per channel
    const std::unique_ptr<float[]> map(new float[3 * m]);
    double block_sums[3 * kBlocks];
    at::parallel_for(0, 3 * kBlocks, 1, [&](int64_t b0, int64_t b1) {
        for (int64_t b = b0; b < b1; ++b) {
            const int64_t c = b / kBlocks, part = b % kBlocks;
            const int i0 = int(part * ho / kBlocks) * wo, i1 = int((part + 1) * ho / kBlocks) * wo;
            const float* m1 = moments.get() + (5 * c + 0) * m;
            const float* my = moments.get() + (5 * c + 1) * m;
            const float* m2 = moments.get() + (5 * c + 2) * m;
            const float* myy = moments.get() + (5 * c + 3) * m;
            const float* m12 = moments.get() + (5 * c + 4) * m;
            float* d1 = p + (3 * c + 0) * m;
            float* d2 = p + (3 * c + 1) * m;
            float* d12 = p + (3 * c + 2) * m;
            float* sm = map.get() + c * m;
            ssim_map(m1, my, m2, myy, m12, d1, d2, d12, sm, i0, i1);
            double sum = 0.0;
            for (int i = i0; i < i1; ++i) sum += sm[i];
            block_sums[b] = sum;
        }
    });
    double sums[3] = {0.0, 0.0, 0.0};
    for (int c = 0; c < 3; ++c) {
        for (int part = 0; part < kBlocks; ++part) sums[c] += block_sums[c * kBlocks + part];
        sums[c] /= m;
    }
    const double total = sums[0] + sums[1] + sums[2];
    return {at::full({}, static_cast<float>(total / 3.0), img.options()), partials};
}

// d(mean SSIM)/d(img) [H, W, 3] times grad (a number), from ssim_forward's partial maps.
at::Tensor ssim_backward(at::Tensor img, at::Tensor ref, at::Tensor partials, double grad) {
    check_images(img, ref);
    img = img.contiguous();
    ref = ref.contiguous();
    const int h = img.size(0), w = img.size(1), ho = h - kTaps + 1, wo = w - kTaps + 1, n = h * w, m = ho * wo;
    TORCH_CHECK(partials.sizes() == at::IntArrayRef({3, 3, ho, wo}), "ssim: partial maps of another size");
    const std::vector<float> g = window();
    auto out = at::empty_like(img);
    const float* x_hwc = img.data_ptr<float>();
    const float* y_hwc = ref.data_ptr<float>();
    const float* p = partials.contiguous().data_ptr<float>();
    float* o = out.data_ptr<float>();
    const float scale = static_cast<float>(grad / (3.0 * m));  // the mean over channels and pixels
    // [channel][the three partial maps][H * W] (every element written before read)
    const std::unique_ptr<float[]> filtered(new float[9 * n]);
    at::parallel_for(0, 9, 1, [&](int64_t j0, int64_t j1) {
        const std::unique_ptr<float[]> tmp(new float[h * (wo + 2 * (kTaps - 1))]);
        for (int64_t j = j0; j < j1; ++j) {
            filter_full(p + j * m, tmp.get(), filtered.get() + j * n, h, w, g.data());
        }
    });
    at::parallel_for(0, n, 2048, [&](int64_t i0, int64_t i1) {
        for (int64_t i = i0; i < i1; ++i) {
            for (int c = 0; c < 3; ++c) {
                const float* f = filtered.get() + 3 * c * n;
                o[3 * i + c] = scale * (f[i] + 2.0f * x_hwc[3 * i + c] * f[n + i] + y_hwc[3 * i + c] * f[2 * n + i]);
            }
        }
    });
    return out;
}

// Registered as operators (torch.ops.tracegs_ssim_cpu.*), not a pybind11 module: the build then needs
// ATen's headers only, not torch/extension.h's (about 5 s of compiling instead of 18). The kernels
// touch no Python objects, and torch.ops calls release the GIL.
TORCH_LIBRARY(tracegs_ssim_cpu, m) {
    m.def("ssim_forward", &ssim_forward);
    m.def("ssim_backward", &ssim_backward);
}
