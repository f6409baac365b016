// The midpoint RK2 of physics/integrate.py (``rk2_scheme`` with the quaternion update of ``rotate``,
// chained over n equal sub-steps with ``params_at``), forward and backward, one particle at a time.
// In PyTorch a sub-step is ~60 element-wise ops on [N, 3] tensors, each with its own autograd node:
// at the demo's sizes the integration cost more than f_trd's matrix products, all of it per-op
// overhead (docs/DESIGN.md, "Fused RK2"). Here a particle's whole path is ~200 flops in registers.
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

namespace {

constexpr int MAX_STEPS = 64;  // sub-steps a backward can replay (the caller falls back beyond)
constexpr double SMALL_ANGLE = 1e-3;  // physics/so3.py: below it, the Taylor series of quat(r)
constexpr double NORM_EPS = 1e-12;    // physics/so3.py quat_normalize's clamp

template <typename T>
struct V3 {
    T x, y, z;
};

template <typename T>
inline V3<T> operator+(V3<T> a, V3<T> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <typename T>
inline V3<T> operator*(T s, V3<T> a) { return {s * a.x, s * a.y, s * a.z}; }
template <typename T>
inline T dot(V3<T> a, V3<T> b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <typename T>
inline V3<T> cross(V3<T> a, V3<T> b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

template <typename T>
struct Q {
    T w, x, y, z;
};

template <typename T>
inline Q<T> mul(Q<T> a, Q<T> b) {  // Hamilton product, as so3.quat_multiply
    return {a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z,
            a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
            a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
            a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}
template <typename T>
inline Q<T> conj(Q<T> a) { return {a.w, -a.x, -a.y, -a.z}; }

// quat(r) = (cos(t/2), sin(t/2)/t r), t = |r| (so3.axis_angle_to_quat); ``dw``, ``ds``: the
// coefficients of r in d(cos(t/2))/dr and d(sin(t/2)/t)/dr.
template <typename T>
inline void axis_angle(V3<T> r, T& w, T& s, T& dw, T& ds) {
    const T u = dot(r, r);
    if (u < T(SMALL_ANGLE * SMALL_ANGLE)) {
        w = T(1) - u / T(8) + u * u / T(384);
        s = T(0.5) - u / T(48) + u * u / T(3840);
        dw = T(-0.25) + u / T(96);
        ds = T(-1) / T(24) + u / T(960);
    } else {
        const T t = std::sqrt(u);
        w = std::cos(t / T(2));
        s = std::sin(t / T(2)) / t;
        dw = -s / T(2);
        ds = (w / T(2) - s) / u;
    }
}

template <typename T>
struct State {
    V3<T> x, v, w;
    Q<T> q;
};

template <typename T>
inline V3<T> load3(const T* p) { return {p[0], p[1], p[2]}; }
template <typename T>
inline void store3(T* p, V3<T> a) { p[0] = a.x; p[1] = a.y; p[2] = a.z; }

// Particle i's state at the start (orientation the identity when only positions move).
template <typename T>
inline State<T> start_state(const T* x, const T* q, const T* v, const T* w, int64_t i, bool rotate) {
    State<T> s{load3(x + 3 * i), load3(v + 3 * i), load3(w + 3 * i), {T(1), T(0), T(0), T(0)}};
    if (rotate) s.q = {q[4 * i], q[4 * i + 1], q[4 * i + 2], q[4 * i + 3]};
    return s;
}

// What a sub-step's backward reads: its start state and the intermediates of its rotation.
template <typename T>
struct Record {
    State<T> start;
    V3<T> x_mid, w_mid, r;  // r = dt w_mid, the rotation vector
    Q<T> dq, m;             // dq = quat(r), m = dq o q before normalising
    T qs, dw, ds, len;      // axis_angle's s and derivative coefficients; |m|
};

// One sub-step, in place; ``rec`` (if given) receives what the backward needs.
template <typename T>
inline void substep(State<T>& s, V3<T> a, V3<T> e, T dt, bool rotate, Record<T>* rec = nullptr) {
    const T h = T(0.5) * dt;
    const V3<T> x_mid = s.x + h * (s.v + cross(s.w, s.x));
    const V3<T> v_mid = s.v + h * a, w_mid = s.w + h * e;
    const V3<T> x_new = s.x + dt * (v_mid + cross(w_mid, x_mid));
    if (rec) *rec = {s, x_mid, w_mid, dt * w_mid, {}, {}, T(0), T(0), T(0), T(0)};
    if (rotate) {
        T qw, qs, dw, ds;
        const V3<T> r = dt * w_mid;
        axis_angle(r, qw, qs, dw, ds);
        const Q<T> dq{qw, qs * r.x, qs * r.y, qs * r.z};
        const Q<T> m = mul(dq, s.q);
        const T len = std::sqrt(m.w * m.w + m.x * m.x + m.y * m.y + m.z * m.z);
        const T norm = std::max(len, T(NORM_EPS));
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
    at::parallel_for(0, n, 2048, [&](int64_t i0, int64_t i1) {
        for (int64_t i = i0; i < i1; ++i) {
            State<T> s = start_state(x, q, v, w, i, rotate);
            const V3<T> ai = load3(a + 3 * i), ei = load3(e + 3 * i);
            for (int64_t k = 0; k < steps; ++k) substep(s, ai, ei, dt, rotate);
            store3(x_out + 3 * i, s.x);
            if (rotate) {
                T* qo = q_out + 4 * i;
                qo[0] = s.q.w, qo[1] = s.q.x, qo[2] = s.q.y, qo[3] = s.q.z;
            }
        }
    });
}

template <typename T>
void backward_kernel(const T* x, const T* q, const T* v, const T* w, const T* a, const T* e,
                     const T* gx_out, const T* gq_out, T* gx0, T* gq0, T* gv0, T* gw0, T* ga0, T* ge0,
                     int64_t n, T dt, int64_t steps, bool rotate) {
    const T h = T(0.5) * dt;
    at::parallel_for(0, n, 2048, [&](int64_t i0, int64_t i1) {
        Record<T> path[MAX_STEPS];
        for (int64_t i = i0; i < i1; ++i) {
            State<T> s = start_state(x, q, v, w, i, rotate);
            const V3<T> ai = load3(a + 3 * i), ei = load3(e + 3 * i);
            for (int64_t k = 0; k < steps; ++k) substep(s, ai, ei, dt, rotate, &path[k]);
            V3<T> gx = load3(gx_out + 3 * i), gv{0, 0, 0}, gw{0, 0, 0}, ga{0, 0, 0}, ge{0, 0, 0};
            Q<T> gq{0, 0, 0, 0};
            if (rotate) gq = {gq_out[4 * i], gq_out[4 * i + 1], gq_out[4 * i + 2], gq_out[4 * i + 3]};
            for (int64_t k = steps - 1; k >= 0; --k) {
                const Record<T>& rec = path[k];
                const State<T>& p = rec.start;
                const V3<T> x_mid = rec.x_mid, w_mid = rec.w_mid;
                // v' = v + dt a, w' = w + dt e: gv, gw pass through to the step's v, w
                ga = ga + dt * gv;
                ge = ge + dt * gw;
                V3<T> g_wmid{0, 0, 0};
                if (rotate) {
                    const Q<T>& m = rec.m;
                    const T len = rec.len;
                    Q<T> gm;
                    if (len > T(NORM_EPS)) {
                        const Q<T> u{m.w / len, m.x / len, m.y / len, m.z / len};
                        const T c = u.w * gq.w + u.x * gq.x + u.y * gq.y + u.z * gq.z;
                        gm = {(gq.w - c * u.w) / len, (gq.x - c * u.x) / len, (gq.y - c * u.y) / len,
                              (gq.z - c * u.z) / len};
                    } else {
                        gm = {gq.w / T(NORM_EPS), gq.x / T(NORM_EPS), gq.y / T(NORM_EPS), gq.z / T(NORM_EPS)};
                    }
                    const Q<T> gdq = mul(gm, conj(p.q));  // d<g, dq o q>/d dq = g o q*
                    gq = mul(conj(rec.dq), gm);           // d<g, dq o q>/d q = dq* o g
                    const V3<T> gvec{gdq.x, gdq.y, gdq.z}, r = rec.r;
                    const V3<T> gr = (gdq.w * rec.dw) * r + rec.qs * gvec + (dot(gvec, r) * rec.ds) * r;
                    g_wmid = dt * gr;
                }
                // x' = x + dt (v_mid + w_mid x x_mid)
                const V3<T> g_u2 = dt * gx;
                g_wmid = g_wmid + cross(x_mid, g_u2);
                const V3<T> g_xmid = cross(g_u2, w_mid);
                // v_mid = v + h a, w_mid = w + h e
                gv = gv + g_u2;
                ga = ga + h * g_u2;
                gw = gw + g_wmid;
                ge = ge + h * g_wmid;
                // x_mid = x + h (v + w x x)
                const V3<T> g_u = h * g_xmid;
                gx = gx + g_xmid + cross(g_u, p.w);
                gv = gv + g_u;
                gw = gw + cross(p.x, g_u);
            }
            store3(gx0 + 3 * i, gx);
            store3(gv0 + 3 * i, gv);
            store3(gw0 + 3 * i, gw);
            store3(ga0 + 3 * i, ga);
            store3(ge0 + 3 * i, ge);
            if (rotate) {
                T* g = gq0 + 4 * i;
                g[0] = gq.w, g[1] = gq.x, g[2] = gq.y, g[3] = gq.z;
            }
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
