// The midpoint RK2 of physics/integrate.py (``rk2_scheme`` with the quaternion update of ``rotate``,
// chained over n equal sub-steps with ``params_at``), forward and backward, particle by particle.
// In PyTorch a sub-step is ~60 element-wise ops on [N, 3] tensors, each with its own autograd node:
// at the demo's sizes the integration cost more than f_trd's matrix products, all of it per-op
// overhead (docs/DESIGN.md, "Fused RK2"). Here a particle's whole path is ~200 flops in registers.
// In float32, 16 particles go through each formula at once (GCC vector extensions: one AVX-512
// register or two AVX2 ones; the lane-by-lane code took 2.5x as long at the demo's sizes); float64
// (the tests' finite differences) runs one particle at a time.
//
// Per sub-step (h = dt / 2; v, w, a, e: equivalent velocity, angular velocity and their rates):
//   x_mid = x + h (v + w x x),   x' = x + dt ((v + h a) + (w + h e) x x_mid),
//   q' = normalize(quat(dt (w + h e)) o q),   v' = v + dt a,   w' = w + dt e.
// The backward replays a particle's sub-steps, recording each one's intermediates (nothing is kept
// from the forward), and runs them in reverse.
// Same formulas, same order of operations as the PyTorch path; results agree to float rounding
// (tests/physics/test_fused_rk2.py).

#include <ATen/core/Tensor.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <vector>

namespace {

constexpr int MAX_STEPS = 64;  // sub-steps a backward can replay (the caller falls back beyond)
constexpr double SMALL_ANGLE = 1e-3;  // physics/so3.py: below it, the Taylor series of quat(r)
constexpr double NORM_EPS = 1e-12;    // physics/so3.py quat_normalize's clamp

// The lanes a kernel computes with: S (one number, or a vector of them) and its element type T.
typedef float floatx16 __attribute__((vector_size(64)));
template <typename T>
struct Lanes {  // one particle at a time
    using S = T;
    static constexpr int64_t W = 1;
};
template <>
struct Lanes<float> {  // 16 particles at a time
    using S = floatx16;
    static constexpr int64_t W = 16;
};
template <typename S>
struct Element {
    using T = S;
};
template <>
struct Element<floatx16> {
    using T = float;
};
template <typename S>
constexpr bool IS_VECTOR = !std::is_same_v<S, typename Element<S>::T>;

// Element-wise sqrt, cos and sin (lane by lane for vectors: std's functions, as the scalar path).
template <typename S>
inline S sqrt_(S u) {
    if constexpr (IS_VECTOR<S>) {
        for (int l = 0; l < 16; ++l) u[l] = std::sqrt(u[l]);
        return u;
    } else {
        return std::sqrt(u);
    }
}
template <typename S>
inline void cos_sin(S t, S& c, S& s) {
    if constexpr (IS_VECTOR<S>) {
        for (int l = 0; l < 16; ++l) c[l] = std::cos(t[l]), s[l] = std::sin(t[l]);
    } else {
        c = std::cos(t), s = std::sin(t);
    }
}

template <typename S>
struct V3 {
    S x, y, z;
};

template <typename S>
inline V3<S> operator+(V3<S> a, V3<S> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <typename K, typename S>
inline V3<S> operator*(K k, V3<S> a) { return {k * a.x, k * a.y, k * a.z}; }  // (K: a number or S)
template <typename S>
inline S dot(V3<S> a, V3<S> b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <typename S>
inline V3<S> cross(V3<S> a, V3<S> b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

template <typename S>
struct Q {
    S w, x, y, z;
};

template <typename S>
inline Q<S> mul(Q<S> a, Q<S> b) {  // Hamilton product, as so3.quat_multiply
    return {a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z,
            a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
            a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
            a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}
template <typename S>
inline Q<S> conj(Q<S> a) { return {a.w, -a.x, -a.y, -a.z}; }

// quat(r) = (cos(t/2), sin(t/2)/t r), t = |r| (so3.axis_angle_to_quat); ``dw``, ``ds``: the
// coefficients of r in d(cos(t/2))/dr and d(sin(t/2)/t)/dr. Vectors take both forms and choose per
// lane (the series' lanes of the other form may hold NaN: not chosen).
template <typename S>
inline void axis_angle(V3<S> r, S& w, S& s, S& dw, S& ds) {
    using T = typename Element<S>::T;
    const S u = dot(r, r);
    const auto series = u < T(SMALL_ANGLE * SMALL_ANGLE);
    if constexpr (!IS_VECTOR<S>) {
        if (series) {
            w = T(1) - u / T(8) + u * u / T(384);
            s = T(0.5) - u / T(48) + u * u / T(3840);
            dw = T(-0.25) + u / T(96);
            ds = T(-1) / T(24) + u / T(960);
            return;
        }
    }
    const S t = sqrt_(u);
    S c, sn;
    cos_sin(t / T(2), c, sn);
    w = c;
    s = sn / t;
    dw = -s / T(2);
    ds = (w / T(2) - s) / u;
    if constexpr (IS_VECTOR<S>) {
        w = series ? T(1) - u / T(8) + u * u / T(384) : w;
        s = series ? T(0.5) - u / T(48) + u * u / T(3840) : s;
        dw = series ? T(-0.25) + u / T(96) : dw;
        ds = series ? T(-1) / T(24) + u / T(960) : ds;
    }
}

template <typename S>
struct State {
    V3<S> x, v, w;
    Q<S> q;
};

// Rows [i, i + count) of a [N, C] tensor's column c, as lanes (missing lanes: ``fill``).
template <typename S, typename T>
inline S load_lanes(const T* p, int64_t i, int64_t count, int64_t cols, int64_t c, T fill = T(0)) {
    if constexpr (IS_VECTOR<S>) {
        S out;
        for (int64_t l = 0; l < 16; ++l) out[l] = l < count ? p[(i + l) * cols + c] : fill;
        return out;
    } else {
        return p[i * cols + c];
    }
}
template <typename S, typename T>
inline void store_lanes(T* p, int64_t i, int64_t count, int64_t cols, int64_t c, S v) {
    if constexpr (IS_VECTOR<S>) {
        for (int64_t l = 0; l < count; ++l) p[(i + l) * cols + c] = v[l];
    } else {
        p[i * cols + c] = v;
    }
}
template <typename S, typename T>
inline V3<S> load3(const T* p, int64_t i, int64_t count) {
    return {load_lanes<S>(p, i, count, 3, 0), load_lanes<S>(p, i, count, 3, 1), load_lanes<S>(p, i, count, 3, 2)};
}
template <typename S, typename T>
inline void store3(T* p, int64_t i, int64_t count, V3<S> a) {
    store_lanes(p, i, count, 3, 0, a.x), store_lanes(p, i, count, 3, 1, a.y), store_lanes(p, i, count, 3, 2, a.z);
}
template <typename S, typename T>
inline Q<S> load4(const T* p, int64_t i, int64_t count, T fill_w = T(1)) {  // (missing lanes: (fill_w, 0, 0, 0))
    return {load_lanes<S>(p, i, count, 4, 0, fill_w), load_lanes<S>(p, i, count, 4, 1),
            load_lanes<S>(p, i, count, 4, 2), load_lanes<S>(p, i, count, 4, 3)};
}
template <typename S, typename T>
inline void store4(T* p, int64_t i, int64_t count, Q<S> a) {
    store_lanes(p, i, count, 4, 0, a.w), store_lanes(p, i, count, 4, 1, a.x);
    store_lanes(p, i, count, 4, 2, a.y), store_lanes(p, i, count, 4, 3, a.z);
}

// Particles [i, i + count)'s state at the start (orientation the identity when only positions move).
template <typename S, typename T>
inline State<S> start_state(const T* x, const T* q, const T* v, const T* w, int64_t i, int64_t count, bool rotate) {
    const S one = S{} + T(1), zero = S{};
    State<S> s{load3<S>(x, i, count), load3<S>(v, i, count), load3<S>(w, i, count), {one, zero, zero, zero}};
    if (rotate) s.q = load4<S>(q, i, count);
    return s;
}

// What a sub-step's backward reads: its start state and the intermediates of its rotation.
template <typename S>
struct Record {
    State<S> start;
    V3<S> x_mid, w_mid, r;  // r = dt w_mid, the rotation vector
    Q<S> dq, m;             // dq = quat(r), m = dq o q before normalising
    S qs, dw, ds, len;      // axis_angle's s and derivative coefficients; |m|
};

// One sub-step, in place; ``rec`` (if given) receives what the backward needs.
template <typename S, typename T>
inline void substep(State<S>& s, V3<S> a, V3<S> e, T dt, bool rotate, Record<S>* rec = nullptr) {
    const T h = T(0.5) * dt;
    const V3<S> x_mid = s.x + h * (s.v + cross(s.w, s.x));
    const V3<S> v_mid = s.v + h * a, w_mid = s.w + h * e;
    const V3<S> x_new = s.x + dt * (v_mid + cross(w_mid, x_mid));
    if (rec) rec->start = s, rec->x_mid = x_mid, rec->w_mid = w_mid, rec->r = dt * w_mid;  // (the rest: below)
    if (rotate) {
        S qw, qs, dw, ds;
        const V3<S> r = dt * w_mid;
        axis_angle(r, qw, qs, dw, ds);
        const Q<S> dq{qw, qs * r.x, qs * r.y, qs * r.z};
        const Q<S> m = mul(dq, s.q);
        const S len = sqrt_(m.w * m.w + m.x * m.x + m.y * m.y + m.z * m.z);
        const auto above = len > T(NORM_EPS);
        const S norm = above ? len : S{} + T(NORM_EPS);  // max(len, NORM_EPS)
        s.q = {m.w / norm, m.x / norm, m.y / norm, m.z / norm};
        if (rec) rec->dq = dq, rec->m = m, rec->qs = qs, rec->dw = dw, rec->ds = ds, rec->len = len;
    }
    s.x = x_new;
    s.v = s.v + dt * a;
    s.w = s.w + dt * e;
}

template <typename T>
void forward_kernel(const T* x, const T* q, const T* v, const T* w, const T* a, const T* e, T* x_out,
                    T* q_out, int64_t n, T dt, int64_t steps, bool rotate) {
    using S = typename Lanes<T>::S;
    constexpr int64_t W = Lanes<T>::W;
    at::parallel_for(0, (n + W - 1) / W, 2048 / W, [&](int64_t b0, int64_t b1) {
        for (int64_t b = b0; b < b1; ++b) {
            const int64_t i = b * W, count = std::min(W, n - i);
            State<S> s = start_state<S>(x, q, v, w, i, count, rotate);
            const V3<S> ai = load3<S>(a, i, count), ei = load3<S>(e, i, count);
            for (int64_t k = 0; k < steps; ++k) substep(s, ai, ei, dt, rotate);
            store3(x_out, i, count, s.x);
            if (rotate) store4(q_out, i, count, s.q);
        }
    });
}

template <typename T>
void backward_kernel(const T* x, const T* q, const T* v, const T* w, const T* a, const T* e,
                     const T* gx_out, const T* gq_out, T* gx0, T* gq0, T* gv0, T* gw0, T* ga0, T* ge0,
                     int64_t n, T dt, int64_t steps, bool rotate) {
    using S = typename Lanes<T>::S;
    constexpr int64_t W = Lanes<T>::W;
    const T h = T(0.5) * dt;
    at::parallel_for(0, (n + W - 1) / W, 2048 / W, [&](int64_t b0, int64_t b1) {
        std::vector<Record<S>> path(steps);
        for (int64_t b = b0; b < b1; ++b) {
            const int64_t i = b * W, count = std::min(W, n - i);
            State<S> s = start_state<S>(x, q, v, w, i, count, rotate);
            const V3<S> ai = load3<S>(a, i, count), ei = load3<S>(e, i, count);
            for (int64_t k = 0; k < steps; ++k) substep(s, ai, ei, dt, rotate, &path[k]);
            const V3<S> zero{S{}, S{}, S{}};
            V3<S> gx = load3<S>(gx_out, i, count), gv = zero, gw = zero, ga = zero, ge = zero;
            Q<S> gq{S{}, S{}, S{}, S{}};
            if (rotate) gq = load4<S>(gq_out, i, count, T(0));
            for (int64_t k = steps - 1; k >= 0; --k) {
                const Record<S>& rec = path[k];
                const State<S>& p = rec.start;
                const V3<S> x_mid = rec.x_mid, w_mid = rec.w_mid;
                // v' = v + dt a, w' = w + dt e: gv, gw pass through to the step's v, w
                ga = ga + dt * gv;
                ge = ge + dt * gw;
                V3<S> g_wmid = zero;
                if (rotate) {
                    const Q<S>& m = rec.m;
                    const S len = rec.len;
                    // normalize's gradient where |m| > NORM_EPS, else the clamp's (lanes choose)
                    const Q<S> u{m.w / len, m.x / len, m.y / len, m.z / len};
                    const S c = u.w * gq.w + u.x * gq.x + u.y * gq.y + u.z * gq.z;
                    const auto above = len > T(NORM_EPS);
                    const T eps = T(NORM_EPS);
                    const Q<S> gm{above ? (gq.w - c * u.w) / len : gq.w / eps,
                                  above ? (gq.x - c * u.x) / len : gq.x / eps,
                                  above ? (gq.y - c * u.y) / len : gq.y / eps,
                                  above ? (gq.z - c * u.z) / len : gq.z / eps};
                    const Q<S> gdq = mul(gm, conj(p.q));  // d<g, dq o q>/d dq = g o q*
                    gq = mul(conj(rec.dq), gm);           // d<g, dq o q>/d q = dq* o g
                    const V3<S> gvec{gdq.x, gdq.y, gdq.z}, r = rec.r;
                    const V3<S> gr = (gdq.w * rec.dw) * r + rec.qs * gvec + (dot(gvec, r) * rec.ds) * r;
                    g_wmid = dt * gr;
                }
                // x' = x + dt (v_mid + w_mid x x_mid)
                const V3<S> g_u2 = dt * gx;
                g_wmid = g_wmid + cross(x_mid, g_u2);
                const V3<S> g_xmid = cross(g_u2, w_mid);
                // v_mid = v + h a, w_mid = w + h e
                gv = gv + g_u2;
                ga = ga + h * g_u2;
                gw = gw + g_wmid;
                ge = ge + h * g_wmid;
                // x_mid = x + h (v + w x x)
                const V3<S> g_u = h * g_xmid;
                gx = gx + g_xmid + cross(g_u, p.w);
                gv = gv + g_u;
                gw = gw + cross(p.x, g_u);
            }
            store3(gx0, i, count, gx);
            store3(gv0, i, count, gv);
            store3(gw0, i, count, gw);
            store3(ga0, i, count, ga);
            store3(ge0, i, count, ge);
            if (rotate) store4(gq0, i, count, gq);
        }
    });
}

void check(const at::Tensor& t, const at::Tensor& like, int64_t cols, const char* what) {
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == like.scalar_type() && t.is_contiguous() &&
                    t.dim() == 2 && t.size(0) == like.size(0) && t.size(1) == cols,
                what, " must be a contiguous CPU tensor [N, ", cols, "] of x's dtype");
}

void check_all(const at::Tensor& x, const at::Tensor& q, const at::Tensor& v, const at::Tensor& w,
               const at::Tensor& a, const at::Tensor& e, bool rotate) {
    TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, "x must be float32 or float64");
    check(x, x, 3, "x");
    if (rotate) check(q, x, 4, "q");
    check(v, x, 3, "v");
    check(w, x, 3, "w");
    check(a, x, 3, "a");
    check(e, x, 3, "e");
}

}  // namespace

// (x [N, 3], q [N, 4] or empty) after ``steps`` sub-steps of ``dt``; q is empty when ``rotate`` is false.
std::vector<at::Tensor> rk2_forward(const at::Tensor& x_in, const at::Tensor& q_in, const at::Tensor& v_in,
                                    const at::Tensor& w_in, const at::Tensor& a_in, const at::Tensor& e_in,
                                    double dt, int64_t steps, bool rotate) {
    const auto x = x_in.detach(), q = q_in.detach(), v = v_in.detach(), w = w_in.detach();
    const auto a = a_in.detach(), e = e_in.detach();
    check_all(x, q, v, w, a, e, rotate);
    auto x_out = at::empty_like(x);
    auto q_out = rotate ? at::empty_like(q) : at::empty({0}, x.options());
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "rk2_forward", [&] {
        forward_kernel<scalar_t>(x.data_ptr<scalar_t>(), rotate ? q.data_ptr<scalar_t>() : nullptr,
                                 v.data_ptr<scalar_t>(), w.data_ptr<scalar_t>(), a.data_ptr<scalar_t>(),
                                 e.data_ptr<scalar_t>(), x_out.data_ptr<scalar_t>(),
                                 rotate ? q_out.data_ptr<scalar_t>() : nullptr, x.size(0), scalar_t(dt),
                                 steps, rotate);
    });
    return {x_out, q_out};
}

// Gradients {x, q (empty unless rotate), v, w, a, e} from those of the outputs x and q.
std::vector<at::Tensor> rk2_backward(const at::Tensor& gx_in, const at::Tensor& gq_in, const at::Tensor& x_in,
                                     const at::Tensor& q_in, const at::Tensor& v_in, const at::Tensor& w_in,
                                     const at::Tensor& a_in, const at::Tensor& e_in, double dt, int64_t steps,
                                     bool rotate) {
    TORCH_CHECK(steps <= MAX_STEPS, "rk2_backward replays at most ", MAX_STEPS, " sub-steps");
    const auto x = x_in.detach(), q = q_in.detach(), v = v_in.detach(), w = w_in.detach();
    const auto a = a_in.detach(), e = e_in.detach();
    check_all(x, q, v, w, a, e, rotate);
    const auto gx = gx_in.detach().contiguous();
    const auto gq = rotate ? gq_in.detach().contiguous() : gq_in;
    check(gx, x, 3, "grad x");
    if (rotate) check(gq, x, 4, "grad q");
    auto out_x = at::empty_like(x), out_v = at::empty_like(x), out_w = at::empty_like(x);
    auto out_a = at::empty_like(x), out_e = at::empty_like(x);
    auto out_q = rotate ? at::empty_like(q) : at::empty({0}, x.options());
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "rk2_backward", [&] {
        backward_kernel<scalar_t>(
            x.data_ptr<scalar_t>(), rotate ? q.data_ptr<scalar_t>() : nullptr, v.data_ptr<scalar_t>(),
            w.data_ptr<scalar_t>(), a.data_ptr<scalar_t>(), e.data_ptr<scalar_t>(), gx.data_ptr<scalar_t>(),
            rotate ? gq.data_ptr<scalar_t>() : nullptr, out_x.data_ptr<scalar_t>(),
            rotate ? out_q.data_ptr<scalar_t>() : nullptr, out_v.data_ptr<scalar_t>(),
            out_w.data_ptr<scalar_t>(), out_a.data_ptr<scalar_t>(), out_e.data_ptr<scalar_t>(), x.size(0),
            scalar_t(dt), steps, rotate);
    });
    return {out_x, out_q, out_v, out_w, out_a, out_e};
}

// Registered as operators (torch.ops.tracegs_rk2_cpu.*), not a pybind11 module: the build then needs
// ATen's headers only, not torch/extension.h's (about 5 s of compiling instead of 18). The kernels
// touch no Python objects, and torch.ops calls release the GIL.
TORCH_LIBRARY(tracegs_rk2_cpu, m) {
    m.def("rk2_forward", &rk2_forward);
    m.def("rk2_backward", &rk2_backward);
}
