// The fields' small float32 MLPs (f_defo, f_trd: 4 x 64 at the cpu-fast sizes) as one op forward
// and one op backward. At ~3500 points x 64 channels a layer's product is a small call for a BLAS
// (~1.5x its FLOP floor) and PyTorch then makes extra passes over the activations for the bias, the
// activation and, in the backward, its derivative and the bias' sum (docs/DESIGN.md, "Fused MLPs";
// the fields take this op where it is built with AVX2 or AVX-512, models/fused_mlp.py).
// Here every product is a register-blocked loop over rows (GCC vector extensions: AVX-512, AVX2 or
// whatever the CPU has) whose result is finished in registers: the forward adds the bias and applies
// the activation before it stores z and h; the backward's input-gradient product applies the
// previous layer's activation derivative before it stores; the weight-gradient product sums the bias
// gradient on the way. Values and gradients agree with the PyTorch layers to float rounding
// (tests/models/test_fused_mlp.py). With ``bf16`` (a build for AVX512-BF16) the forward's and the
// input gradients' products take bf16 operands (rounded to nearest even) with float sums, and so do
// the weights' gradients (bf16 pairs of rows: their sums run over the points).
// The file also holds the fields' other per-step ops that were many small ATen ops: the positional
// encoding and f_defo's output applied to the Gaussians (at the end; tests/models/test_native_field_ops.py).
//
// N: points, L: layers, K: a layer's inputs, O: its outputs; widths are padded to a multiple of PAD
// with zeros (zero weights, zero bias: the padding stays zero through ReLU and SiLU).
// Layer i: z_i = in_i W_i^T + b_i, in_0 = x, in_i = h_{i-1}; the skip layer adds x S^T (Deformable
// 3DGS's concatenation [x, h] with its weight split in two); h_i = act(z_i), except the last layer's
// when ``last_activation`` is false (a linear head). ``stop_from`` >= 0: the last layer's outputs
// from that one on pass no gradient to its input (f_trd's rates, read from its features with their
// gradient stopped). Sums over points (the weights' and biases' gradients) run over fixed blocks of
// rows in a fixed order: the same result for any thread count.
// The fields call it with their parameters whole: the first layer's (and the skip layer's) input as
// the points' encoding and one row every point shares (a frame's encoded time, folded into the bias),
// and the last layer's outputs split into named groups, f_trd's rates scaled as r |r| / scale; the
// products' sums stop at a layer's real widths, not its padding. Each of those was an autograd node
// or two of small ATen ops a call (docs/DESIGN.md, "Fused MLPs").

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <initializer_list>
#include <memory>
#include <type_traits>
#include <utility>
#include <vector>

#if defined(__AVX__)
#include <immintrin.h>
#endif

// bf16 products (mlp_forward's and mlp_backward's ``bf16``) where the compiler targets AVX512-BF16
#if defined(__AVX512F__) && defined(__AVX512BF16__)
#define BF16_PRODUCTS 1
#else
#define BF16_PRODUCTS 0
#endif

namespace {

// Register blocks: the row-wise products keep RB rows x VB vectors of sums, the weight gradients OB
// outputs x GB vectors, within the CPU's vector registers (32 with AVX-512, 16 with AVX2 and SSE).
#if defined(__AVX512F__)
constexpr int VBYTES = 64;
constexpr int RB = 6, VB = 4, OB = 4, GB = 4;
#elif defined(__AVX__)
constexpr int VBYTES = 32;
constexpr int RB = 3, VB = 4, OB = 4, GB = 3;  // (B's fourth vector read from memory by the FMA)
#else
constexpr int VBYTES = 16;  // SSE, NEON
constexpr int RB = 6, VB = 2, OB = 4, GB = 2;
#endif
constexpr int64_t PAD = 16;           // widths padded to a multiple of this (of every vector's lanes)
constexpr int64_t TILE_ROWS = 32;     // rows per parallel task of the row-wise products
constexpr int64_t CHUNK_ROWS = 256;   // rows a thread carries through every layer; a partial sum of the weight gradients

// The forward's and the backward's chunks of points (the same ones: a thread finds its rows in its cache).
inline int64_t chunks_of(int64_t n) { return std::max<int64_t>(1, (n + CHUNK_ROWS - 1) / CHUNK_ROWS); }

template <typename T>
struct VT;
template <>
struct VT<float> {
    typedef float v __attribute__((vector_size(VBYTES)));
};
template <>
struct VT<double> {
    typedef double v __attribute__((vector_size(VBYTES)));
};
template <typename T>
constexpr int64_t LANES = VBYTES / sizeof(T);

enum Activation : int64_t { RELU = 0, SILU = 1, NONE = 2 };

inline int64_t padded(int64_t n) { return (n + PAD - 1) / PAD * PAD; }

template <typename T>
inline typename VT<T>::v loadv(const T* p) {
    typename VT<T>::v v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}
template <typename T>
inline void storev(T* p, typename VT<T>::v v) {
    std::memcpy(p, &v, sizeof(v));
}
// s in every lane, as one broadcast (``V{} + s`` would add a zero first; a loop over the lanes
// becomes lane inserts)
template <typename V, typename T, size_t... I>
inline V splat(T s, std::index_sequence<I...>) {
    return V{((void)I, s)...};
}
template <typename T>
inline typename VT<T>::v broadcast(T s) {
    return splat<typename VT<T>::v>(s, std::make_index_sequence<VBYTES / sizeof(T)>{});
}

// exp(-x) for float lanes in plain arithmetic (std::exp is a call per element): 2^n e^r with
// |r| <= ln2 / 2 and a degree-6 polynomial, relative error ~2e-7. With AVX-512, n is rounded and
// 2^n applied by one instruction each (roundscale, scalef: beyond float's range they give 0 and inf,
// which the sigmoid takes as they are); else n is rounded by adding 1.5 * 2^23, 2^n built in the
// exponent bits, the input clamped. (SiLU's sigmoid is most of an epilogue's work: docs/DESIGN.md.)
inline VT<float>::v exp_poly(VT<float>::v r) {  // e^r for |r| <= ln2 / 2
    VT<float>::v p = r * (1.0f / 720.0f) + (1.0f / 120.0f);
    p = p * r + (1.0f / 24.0f);
    p = p * r + (1.0f / 6.0f);
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    return p * r + 1.0f;
}

// max(lo, min(hi, y)) lane by lane, a NaN kept: one min and one max where the vectors are AVX's
// (GCC's vector conditionals compile to a compare and a blend each).
inline VT<float>::v clamp_lanes(VT<float>::v y, float lo, float hi) {
#if defined(__AVX__) && !defined(__AVX512F__)
    __m256 v;
    std::memcpy(&v, &y, sizeof(v));
    v = _mm256_max_ps(_mm256_set1_ps(lo), _mm256_min_ps(_mm256_set1_ps(hi), v));  // (NaN: the second operand)
    std::memcpy(&y, &v, sizeof(v));
    return y;
#else
    y = y < lo ? lo : y;
    return y > hi ? hi : y;
#endif
}

inline VT<float>::v exp_neg(VT<float>::v x) {
#if defined(__AVX512F__)
    __m512 y;
    std::memcpy(&y, &x, sizeof(y));  // (x, not -x: the signs below are flipped instead)
    const __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(y, _mm512_set1_ps(-1.44269504f)),
                                          _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m512 r = _mm512_fnmsub_ps(n, _mm512_set1_ps(0.693145752f), y);  // -x - n ln2, in two parts
    r = _mm512_fnmadd_ps(n, _mm512_set1_ps(1.42860677e-6f), r);
    VT<float>::v rv, out;
    std::memcpy(&rv, &r, sizeof(rv));
    const VT<float>::v p = exp_poly(rv);
    __m512 pp;
    std::memcpy(&pp, &p, sizeof(pp));
    const __m512 e = _mm512_scalef_ps(pp, n);
    std::memcpy(&out, &e, sizeof(out));
    return out;
#else
    typedef int32_t vi __attribute__((vector_size(VBYTES)));
    VT<float>::v y = clamp_lanes(-x, -87.0f, 88.0f);
    // t = 1.5 * 2^23 + n holds the rounded n in its low mantissa bits: 2^n's exponent bits are t's
    // bits plus the bias, shifted (1.5 * 2^23's own bits end in 23 zeros); no conversion
    const VT<float>::v t = y * 1.44269504f + 12582912.0f, n = t - 12582912.0f;
    const VT<float>::v r = (y - n * 0.693145752f) - n * 1.42860677e-6f;
    vi bits;
    std::memcpy(&bits, &t, sizeof(bits));
    bits = (bits + 127) << 23;
    VT<float>::v scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return exp_poly(r) * scale;
#endif
}

inline VT<double>::v exp_neg(VT<double>::v x) {  // (double: the tests' finite differences)
    VT<double>::v out;
    for (int64_t l = 0; l < LANES<double>; ++l) {
        out[l] = std::exp(-x[l]);
    }
    return out;
}

template <typename T>
inline typename VT<T>::v sigmoid(typename VT<T>::v z) {
    return T(1) / (T(1) + exp_neg(z));
}

// act'(z) g, from z (SiLU) or h (ReLU)
template <typename T>
inline typename VT<T>::v silu_derivative(typename VT<T>::v g, typename VT<T>::v z, typename VT<T>::v s) {
    return g * (s * (T(1) + z * (T(1) - s)));  // (s = sigmoid(z))
}

template <typename T, int64_t ACT>
inline typename VT<T>::v derivative(typename VT<T>::v g, typename VT<T>::v saved) {
    if constexpr (ACT == SILU) {
        return silu_derivative<T>(g, saved, sigmoid<T>(saved));
    } else if constexpr (ACT == RELU) {
        return saved > T(0) ? g : T(0);
    } else {
        return g;
    }
}

// One operand pair of a row-wise product: A [N, K] (row stride lda) times B [K, M] (row stride ldb).
template <typename T>
struct Pair {
    const T* a;
    int64_t lda;
    const T* b;
    int64_t ldb;
    int64_t k;
};

// C = sum over pairs of A B (+ init, a row of M) for rows [r0, r0 + R) and vectors [v0, v0 + NV),
// each result vector handed to epi(row, column, value).
template <int R, int NV, typename T, typename Epi>
inline void block(const std::vector<Pair<T>>& pairs, const T* init, int64_t r0, int64_t v0, Epi& epi) {
    using V = typename VT<T>::v;
    constexpr int64_t L = LANES<T>;
    V acc[R][NV];
    for (int j = 0; j < NV; ++j) {
        const V start = init ? loadv(init + (v0 + j) * L) : V{};
        for (int r = 0; r < R; ++r) {
            acc[r][j] = start;
        }
    }
    for (const Pair<T>& p : pairs) {
        const T* arow = p.a + r0 * p.lda;
        for (int64_t k = 0; k < p.k; ++k) {
            V bv[NV];
            for (int j = 0; j < NV; ++j) {
                bv[j] = loadv(p.b + k * p.ldb + (v0 + j) * L);
            }
            for (int r = 0; r < R; ++r) {
                const V a = broadcast<T>(arow[r * p.lda + k]);
                for (int j = 0; j < NV; ++j) {
                    acc[r][j] += a * bv[j];
                }
            }
        }
    }
    for (int r = 0; r < R; ++r) {
        for (int j = 0; j < NV; ++j) {
            epi(r0 + r, (v0 + j) * L, acc[r][j]);
        }
    }
}

#if BF16_PRODUCTS
// The same product with bf16 operands and float sums (AVX512-BF16's dot product of pairs): A [N, K] as
// bf16 pairs along K (lda: pairs per row), B [K / 2, M, 2] as pairs of its rows (ldb: M), k pairs.
struct PairBF16 {
    const uint32_t* a;
    int64_t lda;
    const uint32_t* b;
    int64_t ldb;
    int64_t k;
};

template <int R, int NV, typename Epi>
inline void block(const std::vector<PairBF16>& pairs, const float* init, int64_t r0, int64_t v0, Epi& epi) {
    __m512 acc[R][NV];
    for (int j = 0; j < NV; ++j) {
        const __m512 start = init ? _mm512_loadu_ps(init + (v0 + j) * 16) : _mm512_setzero_ps();
        for (int r = 0; r < R; ++r) {
            acc[r][j] = start;
        }
    }
    for (const PairBF16& p : pairs) {
        const uint32_t* arow = p.a + r0 * p.lda;
        for (int64_t k = 0; k < p.k; ++k) {
            __m512bh bv[NV];
            for (int j = 0; j < NV; ++j) {
                bv[j] = (__m512bh)_mm512_loadu_si512(p.b + k * p.ldb + (v0 + j) * 16);
            }
            for (int r = 0; r < R; ++r) {
                const __m512bh a = (__m512bh)_mm512_set1_epi32(int(arow[r * p.lda + k]));
                for (int j = 0; j < NV; ++j) {
                    acc[r][j] = _mm512_dpbf16_ps(acc[r][j], a, bv[j]);
                }
            }
        }
    }
    for (int r = 0; r < R; ++r) {
        for (int j = 0; j < NV; ++j) {
            VT<float>::v v;
            std::memcpy(&v, &acc[r][j], sizeof(v));
            epi(r0 + r, (v0 + j) * 16, v);
        }
    }
}

inline void store_bf16(uint16_t* p, VT<float>::v v) {  // rounded to nearest even
    __m512 f;
    std::memcpy(&f, &v, sizeof(f));
    const __m256bh b = _mm512_cvtneps_pbh(f);
    std::memcpy(p, &b, sizeof(b));
}
#else
inline void store_bf16(uint16_t*, VT<float>::v) {}  // (never called: no bf16 products in this build)
#endif

template <typename P>
struct Sum;  // the sums' (and init's) type of a product's operands
template <typename T>
struct Sum<Pair<T>> {
    using type = T;
};
#if BF16_PRODUCTS
template <>
struct Sum<PairBF16> {
    using type = float;
};
#endif

template <int R, typename P, typename Epi>
inline void block_row(const std::vector<P>& pairs, const typename Sum<P>::type* init, int64_t r0, int64_t vectors,
                      Epi& epi) {
    int64_t v0 = 0;
    for (; v0 + VB <= vectors; v0 += VB) {
        block<R, VB>(pairs, init, r0, v0, epi);
    }
    for (; v0 < vectors; ++v0) {
        block<R, 1>(pairs, init, r0, v0, epi);
    }
}

// Whether an epilogue applies its activation after each tile (``finish``) rather than in the block.
template <typename E, typename = void>
struct Defers : std::false_type {};
template <typename E>
struct Defers<E, std::void_t<decltype(E::defers)>> : std::bool_constant<E::defers> {};

// Tiles [t0, t1) of a row-wise product (a deferred activation after each). Not inlined: with one
// thread at::parallel_for calls its body in place, and inlined there the product's loops were
// compiled anew, with SiLU's constants held in vector registers and the sums spilled to the stack
// (1.5x as long as the same code called by the threads); one function serves both (the chunks'
// products, chunk_product).
template <typename P, typename Epi>
__attribute__((noinline)) void product_tiles(const std::vector<P>& pairs, const typename Sum<P>::type* init,
                                             int64_t n, int64_t vectors, int64_t t0, int64_t t1, Epi& epi) {
    for (int64_t t = t0; t < t1; ++t) {
        const int64_t end = std::min(n, (t + 1) * TILE_ROWS);
        int64_t r = t * TILE_ROWS;
        for (; r + RB <= end; r += RB) {
            block_row<RB>(pairs, init, r, vectors, epi);
        }
        for (; r < end; ++r) {
            block_row<1>(pairs, init, r, vectors, epi);
        }
        if constexpr (Defers<Epi>::value) {
            epi.finish(t * TILE_ROWS, end, vectors * LANES<typename Sum<P>::type>);
        }
    }
}

// Column c of rows r + AHEAD and r + AHEAD + 1 of src [cr, w] asked of the memory now (where they are
// rows of it): the backward's first reads of what the forward kept come from memory (the other calls
// ran between), and a chunk's rows were too short a stream for the hardware prefetcher to run ahead
// of them.
constexpr int64_t AHEAD = 8;
template <typename T>
inline void prefetch_rows(const T* src, int64_t r, int64_t cr, int64_t w, int64_t c) {
    if (r + AHEAD + 1 < cr) {
        __builtin_prefetch(src + (r + AHEAD) * w + c, 0, 3);
        __builtin_prefetch(src + (r + AHEAD + 1) * w + c, 0, 3);
    }
}

// One chunk's share of db = the column sums of D (rows [0, cr) of D [., m]); nothing where pb is null.
// Up to SB vectors of a row at a time, each its own sum over the rows in order (one sum a column
// was a chain of dependent adds down a strided column).
template <typename T>
void bias_partial(const T* d, int64_t m, int64_t cr, T* pb) {
    using V = typename VT<T>::v;
    constexpr int64_t L = LANES<T>;
    constexpr int SB = 8;
    for (int64_t v0 = 0; pb != nullptr && v0 < m / L; v0 += SB) {
        const int nv = int(std::min<int64_t>(SB, m / L - v0));
        V s[SB] = {};
        for (int64_t r = 0; r < cr; ++r) {
            for (int j = 0; j < SB; ++j) {
                if (j < nv) {
                    s[j] += loadv(d + r * m + (v0 + j) * L);
                }
            }
        }
        for (int j = 0; j < nv; ++j) {
            storev(pb + (v0 + j) * L, s[j]);
        }
    }
}

// One chunk's share of dW = D^T In and (unless pb is null) of db = the column sums of D: rows [0, cr)
// of D [., m] and In [., k] (padded widths, row strides m and k), into pw [m, k] (its rows up to m_out
// rounded up to OB) and pb [m]. The chunks are CHUNK_ROWS rows of the points, summed in order by
// reduce_partials: the same sums for any thread count.
template <typename T>
void weight_partial(const T* d, int64_t m, const T* in, int64_t k, int64_t cr, T* pw, T* pb, int64_t m_out) {
    using V = typename VT<T>::v;
    constexpr int64_t L = LANES<T>;
    const int64_t kv = k / L;
    for (int64_t o0 = 0; o0 < m_out; o0 += OB) {  // (m_out rounded up to OB <= m: PAD's multiple)
        for (int64_t v0 = 0; v0 < kv; v0 += GB) {
            const int nv = int(std::min<int64_t>(GB, kv - v0));
            V acc[OB][GB] = {};
            for (int64_t r = 0; r < cr; ++r) {
                V iv[GB];
                for (int j = 0; o0 == 0 && j < nv; ++j) {  // (the first pass over In's rows: from memory)
                    prefetch_rows(in, r, cr, k, (v0 + j) * L);
                }
                for (int j = 0; j < GB; ++j) {
                    iv[j] = j < nv ? loadv(in + r * k + (v0 + j) * L) : V{};
                }
                for (int o = 0; o < OB; ++o) {
                    const V dv = broadcast<T>(d[r * m + o0 + o]);
                    for (int j = 0; j < GB; ++j) {
                        acc[o][j] += dv * iv[j];
                    }
                }
            }
            for (int o = 0; o < OB; ++o) {
                for (int j = 0; j < nv; ++j) {
                    storev(pw + (o0 + o) * k + (v0 + j) * L, acc[o][j]);
                }
            }
        }
    }
    bias_partial<T>(d, m, cr, pb);
}

#if BF16_PRODUCTS
// 16 bf16 values of one row (upper) and of the next (lower) stored as 16 pairs, (upper's, lower's).
inline void store_pair16(__m256i upper, __m256i lower, uint32_t* dst) {
    alignas(64) static const uint16_t order[32] = {0, 16, 1, 17, 2,  18, 3,  19, 4,  20, 5,  21, 6,  22, 7,  23,
                                                   8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31};
    const __m512i both = _mm512_inserti64x4(_mm512_castsi256_si512(upper), lower, 1);
    _mm512_storeu_si512(dst, _mm512_permutexvar_epi16(_mm512_load_si512(order), both));
}

// store_pair16 of 16 floats of each row, rounded to the nearest even bf16.
inline void store_pair(__m512 upper, __m512 lower, uint32_t* dst) {
    const __m256bh a = _mm512_cvtneps_pbh(upper), b = _mm512_cvtneps_pbh(lower);
    __m256i ai, bi;
    std::memcpy(&ai, &a, sizeof(ai));
    std::memcpy(&bi, &b, sizeof(bi));
    store_pair16(ai, bi, dst);
}

// Rows [0, cr) of a float matrix [., w] (row stride w, a multiple of 16) as bf16 pairs of consecutive
// rows, [ceil(cr / 2), w] (each value rounded to the nearest even; an odd count's last pair with a
// zero): an operand of the weight gradients' bf16 products, whose sums run over rows.
inline void row_pairs(const float* src, int64_t cr, int64_t w, uint32_t* dst) {
    for (int64_t r = 0; r < cr; r += 2) {
        for (int64_t c = 0; c < w; c += 16) {
            prefetch_rows(src, r, cr, w, c);
            store_pair(_mm512_loadu_ps(src + r * w + c),
                       r + 1 < cr ? _mm512_loadu_ps(src + (r + 1) * w + c) : _mm512_setzero_ps(), dst + r / 2 * w + c);
        }
    }
}

// row_pairs of rows already bf16 (row stride w, a multiple of 16): the bf16 mode's saved x.
inline void row_pairs16(const uint16_t* src, int64_t cr, int64_t w, uint32_t* dst) {
    for (int64_t r = 0; r < cr; r += 2) {
        for (int64_t c = 0; c < w; c += 16) {
            prefetch_rows(src, r, cr, w, c);
            const __m256i a = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(src + r * w + c));
            const __m256i b = r + 1 < cr ? _mm256_loadu_si256(reinterpret_cast<const __m256i*>(src + (r + 1) * w + c))
                                         : _mm256_setzero_si256();
            store_pair16(a, b, dst + r / 2 * w + c);
        }
    }
}

// A SiLU layer's rows for the backward from its kept z [cr, w]: sigmoid(z) into ``sig`` (the input
// gradient's derivative reads it) and h = z sigmoid(z) straight into row_pairs' bf16 pairs (the weight
// gradient's operand; no float h stored and read back). The same values as the float path's.
inline void silu_row_pairs(const float* z, int64_t cr, int64_t w, float* sig, uint32_t* dst) {
    for (int64_t r = 0; r < cr; r += 2) {
        for (int64_t c = 0; c < w; c += 16) {
            prefetch_rows(z, r, cr, w, c);
            const VT<float>::v za = loadv(z + r * w + c), sa = sigmoid<float>(za);
            storev(sig + r * w + c, sa);
            __m512 lower = _mm512_setzero_ps();
            if (r + 1 < cr) {
                const VT<float>::v zb = loadv(z + (r + 1) * w + c), sb = sigmoid<float>(zb);
                storev(sig + (r + 1) * w + c, sb);
                lower = __m512(zb * sb);
            }
            store_pair(__m512(za * sa), lower, dst + r / 2 * w + c);
        }
    }
}

// Outputs [o0, o0 + OB) x vectors [v0, v0 + NV) of weight_partial_bf16's sums (NV a constant: the sums
// stay in registers).
template <int NV>
inline void weight_block_bf16(const uint32_t* d2, int64_t m, const uint32_t* in2, int64_t k, int64_t pairs,
                              int64_t o0, int64_t v0, float* pw) {
    __m512 acc[OB][NV];
    for (int o = 0; o < OB; ++o) {
        for (int j = 0; j < NV; ++j) {
            acc[o][j] = _mm512_setzero_ps();
        }
    }
    for (int64_t p = 0; p < pairs; ++p) {
        __m512bh iv[NV];
        for (int j = 0; j < NV; ++j) {
            iv[j] = (__m512bh)_mm512_loadu_si512(in2 + p * k + (v0 + j) * 16);
        }
        for (int o = 0; o < OB; ++o) {
            const __m512bh dv = (__m512bh)_mm512_set1_epi32(int(d2[p * m + o0 + o]));
            for (int j = 0; j < NV; ++j) {
                acc[o][j] = _mm512_dpbf16_ps(acc[o][j], dv, iv[j]);
            }
        }
    }
    for (int o = 0; o < OB; ++o) {
        for (int j = 0; j < NV; ++j) {
            _mm512_storeu_ps(pw + (o0 + o) * k + (v0 + j) * 16, acc[o][j]);
        }
    }
}

// weight_partial with bf16 products: dW's chunk share from the rows' bf16 pairs (row_pairs' of D,
// d2 [., m], and of In, in2 [., k]), float sums; db from the float rows of D.
inline void weight_partial_bf16(const float* d, const uint32_t* d2, int64_t m, const uint32_t* in2, int64_t k,
                                int64_t cr, float* pw, float* pb, int64_t m_out) {
    const int64_t kv = k / 16, pairs = (cr + 1) / 2;
    static_assert(GB == 4, "weight_partial_bf16 takes GB vectors or 1-3");
    for (int64_t o0 = 0; o0 < m_out; o0 += OB) {
        int64_t v0 = 0;
        for (; v0 + GB <= kv; v0 += GB) {
            weight_block_bf16<GB>(d2, m, in2, k, pairs, o0, v0, pw);
        }
        switch (kv - v0) {
            case 3: weight_block_bf16<3>(d2, m, in2, k, pairs, o0, v0, pw); break;
            case 2: weight_block_bf16<2>(d2, m, in2, k, pairs, o0, v0, pw); break;
            case 1: weight_block_bf16<1>(d2, m, in2, k, pairs, o0, v0, pw); break;
            default: break;
        }
    }
    bias_partial<float>(d, m, cr, pb);
}
#endif

// silu_row_pairs where the products are bf16 (float, an AVX512-BF16 build): whether it made the pairs.
template <typename T>
bool silu_pairs(const T* z, int64_t cr, int64_t w, T* sig, uint32_t* dst) {
#if BF16_PRODUCTS
    if constexpr (std::is_same_v<T, float>) {
        silu_row_pairs(z, cr, w, sig, dst);
        return true;
    }
#endif
    return false;
}

// A chunk's partials of layer i's weight gradient (weight_partial's: D [cr, m] with In [cr, k], and its
// bias') and, where ps is not null, of the skip weight's (D with the points' X [cr, ke]): from bf16
// pairs of rows where ``pairs`` is not null (bf16 products; a thread's scratch, two halves of ``half``;
// ``in`` null: In's pairs are in the second half already, silu_row_pairs'; with bf16 products the
// points' X comes as bf16 rows, x16: the saved x of a bf16 call, which is In where ``in_is_x``).
template <typename T>
void layer_partials(const T* d, int64_t m, const T* in, int64_t k, const T* x, int64_t ke, int64_t cr, T* pw,
                    int64_t m_out, T* ps, int64_t s_out, uint32_t* pairs, int64_t half, const uint16_t* x16,
                    bool in_is_x) {
#if BF16_PRODUCTS
    if constexpr (std::is_same_v<T, float>) {
        if (pairs != nullptr) {  // (rounded as the other products' operands)
            uint32_t* in2 = pairs + half;
            row_pairs(d, cr, m, pairs);
            if (in_is_x) {
                row_pairs16(x16, cr, k, in2);
            } else if (in != nullptr) {
                row_pairs(in, cr, k, in2);
            }
            weight_partial_bf16(d, pairs, m, in2, k, cr, pw, pw + m * k, m_out);
            if (ps != nullptr) {
                row_pairs16(x16, cr, ke, in2);
                weight_partial_bf16(d, pairs, m, in2, ke, cr, ps, nullptr, s_out);
            }
            return;
        }
    }
#endif
    weight_partial<T>(d, m, in, k, cr, pw, pw + m * k, m_out);
    if (ps != nullptr) {
        weight_partial<T>(d, m, x, ke, cr, ps, nullptr, s_out);
    }
}

// dw [m_out, k_out] (contiguous) and db [m_out] (none where null) from the chunks' partials
// (weight_partial's, each [m, k] then [m]), added in chunk order a vector at a time (the same sums as
// element by element).
template <typename T>
void reduce_partials(T* partial, int64_t chunks, int64_t m, int64_t k, T* dw, T* db, int64_t m_out, int64_t k_out) {
    constexpr int64_t L = LANES<T>;
    const int64_t size = m * k + m, rows = (m_out + OB - 1) / OB * OB;  // (the rows the chunks wrote)
    for (int64_t c = 1; c < chunks; ++c) {
        const T* part = partial + c * size;
        for (int64_t e = 0; e < rows * k; e += L) {
            storev(partial + e, loadv(partial + e) + loadv(part + e));
        }
        for (int64_t e = m * k; db != nullptr && e < size; e += L) {
            storev(partial + e, loadv(partial + e) + loadv(part + e));
        }
    }
    for (int64_t o = 0; o < m_out; ++o) {
        std::copy(partial + o * k, partial + o * k + k_out, dw + o * k_out);
        if (db != nullptr) {
            db[o] = partial[m * k + o];
        }
    }
}

inline at::Tensor as_type(const at::Tensor& t, at::ScalarType type) {
    return t.scalar_type() == type ? t : t.to(type);
}

// Columns [c, c + lanes) of a row of n floats, those from n on zero: a masked load with AVX2 or AVX-512
// (nothing past the row read), else lane by lane. (A row's std::copy of ~40 floats and its padding's fill were
// two library calls a row: ~10% of a forward at the fields' sizes.)
inline VT<float>::v load_part(const float* row, int64_t c, int64_t n) {
    VT<float>::v v;
#if defined(__AVX512F__)
    const int64_t left = n - c;
    const __mmask16 keep = left >= 16 ? __mmask16(0xFFFF) : left > 0 ? __mmask16((1u << left) - 1) : __mmask16(0);
    const __m512 x = _mm512_maskz_loadu_ps(keep, row + c);
    std::memcpy(&v, &x, sizeof(v));
#elif defined(__AVX2__)
    const __m256i lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256i keep = _mm256_cmpgt_epi32(_mm256_set1_epi32(int(std::min<int64_t>(n - c, 8))), lanes);
    const __m256 x = _mm256_maskload_ps(row + c, keep);
    std::memcpy(&v, &x, sizeof(v));
#else
    for (int64_t l = 0; l < LANES<float>; ++l) {
        v[l] = c + l < n ? row[c + l] : 0.0f;
    }
#endif
    return v;
}

// Rows [r0, r1) of a matrix w [rows, cols] (of type T, any strides) copied into o (row stride pc >=
// cols, from its row r0), each row's padding zeroed: ``pack``'s loop, and the forward's input packed
// a chunk at a time by the thread that takes it.
template <typename T>
void pack_rows(const at::Tensor& w, int64_t r0, int64_t r1, T* o, int64_t pc) {
    const int64_t cols = w.size(1), rs = w.stride(0), cs = w.stride(1);
    const T* src = w.data_ptr<T>();
    for (int64_t r = r0; r < r1; ++r) {
        if (cs == 1) {  // (the fields' inputs, [N, E])
            if constexpr (std::is_same_v<T, float>) {  // (a vector at a time, the padding with it)
                for (int64_t c = 0; c < pc; c += LANES<float>) {
                    storev(o + r * pc + c, load_part(src + r * rs, c, cols));
                }
                continue;
            }
            std::copy(src + r * rs, src + r * rs + cols, o + r * pc);
        } else {
            for (int64_t c = 0; c < cols; ++c) {
                o[r * pc + c] = src[r * rs + c * cs];
            }
        }
        std::fill(o + r * pc + cols, o + (r + 1) * pc, T(0));
    }
}

// A matrix [rows, cols] (any strides and floating type) copied as T into a zero-padded [padded rows,
// padded cols] buffer, transposed if asked ([cols, rows] -> its transpose's padding), its rows from
// keep_rows on left zero. Plain loops, no ATen ops: the op packs every layer each call.
template <typename T>
at::Tensor pack(const at::Tensor& w0, bool transpose, int64_t keep_rows = -1) {
    constexpr auto type = c10::CppTypeToScalarType<T>::value;
    const at::Tensor w = transpose ? as_type(w0, type).t() : as_type(w0, type);
    const int64_t rows = w.size(0), pc = padded(w.size(1));
    const int64_t kept = keep_rows >= 0 && keep_rows < rows ? keep_rows : rows;
    at::Tensor out = at::empty({padded(rows), pc}, w.options());
    T* o = out.data_ptr<T>();
    pack_rows<T>(w, 0, kept, o, pc);
    std::fill(o + kept * pc, o + out.numel(), T(0));
    return out;
}

template <typename T>
at::Tensor pad_vector(const at::Tensor& b0) {
    constexpr auto type = c10::CppTypeToScalarType<T>::value;
    const at::Tensor b = as_type(b0, type);
    at::Tensor out = at::empty({padded(b.size(0))}, b.options());
    T* o = out.data_ptr<T>();
    const T* src = b.data_ptr<T>();
    std::fill(o, o + out.numel(), T(0));
    for (int64_t i = 0; i < b.size(0); ++i) {
        o[i] = src[i * b.stride(0)];
    }
    return out;
}

inline bool activates(int64_t i, int64_t layers, bool last_activation) {
    return i < layers - 1 || last_activation;
}

// A result vector also stored as bf16 (the next bf16 product's operand) where ``copy`` is not null.
template <typename T>
inline void store_copy(uint16_t* copy, int64_t at, typename VT<T>::v v) {
    if constexpr (std::is_same_v<T, float>) {
        if (copy != nullptr) {
            store_bf16(copy + at, v);
        }
    }
}

// The forward's epilogue (the bias is in the sums): z kept where the backward reads it (``kept``: z
// for SiLU and for the linear last layer, h for ReLU; null: nothing kept, no gradient to come), and
// h (with its bf16 copy for the next bf16 product) for the next layer (null: the last layer's is kept).
// With AVX2's 16 vector registers SiLU is applied after each tile's products (``defers``): z is
// stored as h, and ``finish`` turns a tile's rows of h into SiLU(z) in a loop of its own. Inside the
// register block the sigmoid's constants and temporaries did not fit beside the 12 sums, and its chain
// of dependent operations ran one result vector at a time (the epilogue took ~3x AVX-512's time per
// lane); the same arithmetic, the same bits.
#if defined(__AVX__) && !defined(__AVX512F__)
constexpr bool DEFER_SILU = true;
#else
constexpr bool DEFER_SILU = false;
#endif

// A kept vector (read by the backward, after the other calls): a streaming store with AVX-512 (no read
// of the line first; kept + at is 64-byte aligned), else storev.
template <typename T>
inline void store_kept(T* p, typename VT<T>::v v) {
#if defined(__AVX512F__)
    if constexpr (std::is_same_v<T, float>) {
        __m512 f;
        std::memcpy(&f, &v, sizeof(f));
        _mm512_stream_ps(p, f);
        return;
    }
#endif
    storev(p, v);
}

template <typename T, int64_t ACT>
struct ForwardStore {
    static constexpr bool defers = DEFER_SILU && ACT == SILU && std::is_same_v<T, float>;
    T* kept;
    T* h;
    int64_t ld;
    uint16_t* h_bf16;  // (never with ``defers``: bf16 products need AVX-512)
    void operator()(int64_t r, int64_t c, typename VT<T>::v v) {
        const int64_t at = r * ld + c;
        if constexpr (defers) {
            if (kept != nullptr) {
                storev(kept + at, v);
            }
            storev(h + at, v);
        } else if constexpr (ACT == SILU || ACT == RELU) {
            typename VT<T>::v a;
            if constexpr (ACT == SILU) {
                a = v * sigmoid<T>(v);
            } else {
                a = v > T(0) ? v : T(0);
            }
            if (kept != nullptr) {
                store_kept<T>(kept + at, ACT == SILU ? v : a);
            }
            if (h != nullptr) {
                storev(h + at, a);
            }
            store_copy<T>(h_bf16, at, a);
        } else {
            storev(kept + at, v);
        }
    }
    void finish(int64_t r0, int64_t r1, int64_t cols) {  // (``defers``: rows [r0, r1) of h, z -> SiLU(z))
        for (int64_t r = r0; r < r1; ++r) {
            for (int64_t c = 0; c < cols; c += LANES<T>) {
                const typename VT<T>::v z = loadv(h + r * ld + c);
                storev(h + r * ld + c, z * sigmoid<T>(z));
            }
        }
    }
};

template <typename T, int64_t ACT>
struct BackwardStore {  // dz_{i-1} = (dz_i W_i) act'(z_{i-1}), from z and its sigmoid (SiLU) or h (ReLU)
    T* out;
    const T* saved;
    const T* sig;  // sigmoid(z_{i-1}) (SiLU)
    int64_t ld;
    uint16_t* out_bf16;  // dz_{i-1} as bf16, or null
    void operator()(int64_t r, int64_t c, typename VT<T>::v v) {
        const int64_t at = r * ld + c;
        typename VT<T>::v d;
        if constexpr (ACT == SILU) {
            d = silu_derivative<T>(v, loadv(saved + at), loadv(sig + at));
        } else {
            d = derivative<T, ACT>(v, loadv(saved + at));
        }
        storev(out + at, d);
        store_copy<T>(out_bf16, at, d);
    }
};

// Rows [r0, r1) of x [N, E] float32 (its columns contiguous) as bf16 rows of ke columns (the padding
// zero), each value rounded to the nearest even, into dst from its row r0: the operand A of bf16 products.
inline void pack_rows_bf16(const at::Tensor& x, int64_t r0, int64_t r1, uint16_t* dst, int64_t ke) {
    TORCH_CHECK(x.stride(1) == 1, "pack_rows_bf16: x's columns must be contiguous");
    const float* src = x.data_ptr<float>();
    for (int64_t r = r0; r < r1; ++r) {
        for (int64_t c = 0; c < ke; c += LANES<float>) {
            store_copy<float>(dst + r * ke, c, load_part(src + r * x.stride(0), c, x.size(1)));
        }
    }
}

inline uint16_t* bf16_data(const at::Tensor& t) {
    return reinterpret_cast<uint16_t*>(t.data_ptr<at::BFloat16>());
}

// Rows [r0, r1) of the last layer's output h (padded) into the output groups (each [N, its columns]),
// those from column ``scaled_from`` on (>= 0) as r |r| / scale (as ATen: the product, then the division).
template <typename T>
void write_groups(const at::Tensor& h, int64_t r0, int64_t r1, const std::vector<at::Tensor>& groups,
                  int64_t scaled_from, double scale) {
    const T* hp = h.data_ptr<T>();
    const int64_t ld = h.size(1);
    const T s = T(scale);
    for (int64_t g = 0, c0 = 0; g < int64_t(groups.size()); c0 += groups[g].size(1), ++g) {
        const int64_t cols = groups[g].size(1);
        T* op = groups[g].data_ptr<T>();
        for (int64_t r = r0; r < r1; ++r) {
            for (int64_t c = 0; c < cols; ++c) {
                const T v = hp[r * ld + c0 + c];
                op[r * cols + c] = scaled_from >= 0 && c0 + c >= scaled_from ? v * std::abs(v) / s : v;
            }
        }
    }
}

// The operand B of a bf16 product: ``pack``'s padded [K, M] matrix as pairs of its rows [K / 2, M, 2],
// each rounded to the nearest bf16.
at::Tensor pack_pairs(const at::Tensor& w, bool transpose, int64_t keep_rows = -1) {
    const at::Tensor f = pack<float>(w, transpose, keep_rows);
    const int64_t kp = f.size(0), mp = f.size(1);
    at::Tensor out = at::empty({kp / 2, mp, 2}, f.options().dtype(at::kBFloat16));
    const float* src = f.data_ptr<float>();
    at::BFloat16* dst = out.data_ptr<at::BFloat16>();
    for (int64_t k = 0; k < kp / 2; ++k) {
        for (int64_t c = 0; c < mp; ++c) {
            dst[(k * mp + c) * 2] = at::BFloat16(src[2 * k * mp + c]);
            dst[(k * mp + c) * 2 + 1] = at::BFloat16(src[(2 * k + 1) * mp + c]);
        }
    }
    return out;
}

inline const uint32_t* pairs_of(const at::Tensor& t) {
    return reinterpret_cast<const uint32_t*>(t.data_ptr<at::BFloat16>());
}

// The rows of B = w^T (``transpose``) or w (its rows from ``keep`` on left zero) that are not padding:
// the products' sums stop there (a head's 3 outputs, not 16; a first layer's 39 encoded inputs, not 48).
inline int64_t real_rows(const at::Tensor& w, bool transpose, int64_t keep) {
    const int64_t rows = w.size(transpose ? 1 : 0);
    return keep >= 0 && keep < rows ? keep : rows;
}

// A weight w [O, K] packed once as a product's operand B for every chunk: transposed, [K padded,
// O padded] (the forward's), or as it is, [O padded, K padded] with its rows from ``keep`` on zero (the
// input gradients'), in float or as bf16 pairs; and how many of its rows (float) or pairs of rows
// (bf16) the sums run over.
struct PackedB {
    at::Tensor b;
    int64_t k = 0;
    bool bf16 = false;
};

template <typename T>
PackedB pack_b(const at::Tensor& w, bool transpose, int64_t keep, bool bf16) {
    const int64_t k = real_rows(w, transpose, keep);
#if BF16_PRODUCTS
    if constexpr (std::is_same_v<T, float>) {
        if (bf16) {
            return {pack_pairs(w, transpose, keep), (k + 1) / 2, true};
        }
    }
#endif
    return {pack<T>(w, transpose, keep), k, false};
}

// One operand pair of a chunk's product: A's rows from the chunk's first, in float (a) or as bf16
// (a16, where B is bf16 pairs), row stride lda; and B.
template <typename T>
struct Operand {
    const PackedB* b;
    const T* a;
    const uint16_t* a16;
    int64_t lda;
};

// Rows [0, cr) of the sum over ``ops`` of A B (+ init, a row), each result vector to epi(row within the
// chunk, column, value); in the calling thread (one chunk's task).
template <typename T, typename Epi>
void chunk_product(std::initializer_list<Operand<T>> ops, const T* init, int64_t cr, Epi epi) {
    const int64_t tiles = (cr + TILE_ROWS - 1) / TILE_ROWS;
    const PackedB& first = *ops.begin()->b;
#if BF16_PRODUCTS
    if constexpr (std::is_same_v<T, float>) {
        if (first.bf16) {
            std::vector<PairBF16> pairs;
            for (const Operand<T>& op : ops) {
                pairs.push_back({reinterpret_cast<const uint32_t*>(op.a16), op.lda / 2, pairs_of(op.b->b),
                                 op.b->b.size(1), op.b->k});
            }
            product_tiles(pairs, init, cr, first.b.size(1) / LANES<float>, 0, tiles, epi);
            return;
        }
    }
#endif
    std::vector<Pair<T>> pairs;
    for (const Operand<T>& op : ops) {
        pairs.push_back({op.a, op.lda, op.b->b.template data_ptr<T>(), op.b->b.size(1), op.b->k});
    }
    product_tiles(pairs, init, cr, first.b.size(1) / LANES<T>, 0, tiles, epi);
}

template <typename T, typename Fn>
void with_activation(int64_t act, Fn fn) {
    if (act == SILU) {
        fn(std::integral_constant<int64_t, SILU>{});
    } else if (act == RELU) {
        fn(std::integral_constant<int64_t, RELU>{});
    } else {
        fn(std::integral_constant<int64_t, NONE>{});
    }
}

// The encoding of the first layer (and of the skip layer) in two parts (``time_row`` defined): x's
// columns [0, ex) of those layers' weights, then [ex, encoded) for one row t [1, encoded - ex] that
// every point shares (the encoded time of a frame), whose product is folded into the layer's bias; the
// skip layer's weight holds its hidden input's columns after ``encoded``. The weights stay the module's
// parameters, whole: no slices, no one-row products and no sums of their gradients in autograd.
struct Parts {
    at::Tensor time;  // [1, encoded - ex] (undefined: x is the whole encoding, the weights as given)
    int64_t ex = 0, encoded = 0;
    bool defined() const { return time.defined(); }
};

// The weights as the products take them: with parts, the first layer's x columns, and the skip
// layer's hidden columns with its x columns as the skip weight.
void take_parts(const Parts& parts, std::vector<at::Tensor>& weights, c10::optional<at::Tensor>& skip_weight,
                int64_t skip_layer) {
    if (!parts.defined()) {
        return;
    }
    TORCH_CHECK(weights[0].size(1) == parts.encoded, "fused MLP: the first layer does not take the encoding");
    TORCH_CHECK(!skip_weight.has_value(), "fused MLP: with a time row the skip layer's weight is whole");
    TORCH_CHECK(skip_layer != 0, "fused MLP: with a time row the skip layer follows the first");
    if (skip_layer >= 0) {
        const at::Tensor whole = weights[skip_layer];
        TORCH_CHECK(whole.size(1) > parts.encoded, "fused MLP: the skip layer does not take the encoding");
        skip_weight = whole.narrow(1, 0, parts.ex);
        weights[skip_layer] = whole.narrow(1, parts.encoded, whole.size(1) - parts.encoded);
    }
    weights[0] = weights[0].narrow(1, 0, parts.ex);
}

// b + t W_t^T: a layer's bias with the time row's product folded in (W_t: the layer's time columns).
template <typename T>
at::Tensor fold_time(const at::Tensor& b0, const at::Tensor& layer_weight, const Parts& parts) {
    constexpr auto type = c10::CppTypeToScalarType<T>::value;
    const at::Tensor b = as_type(b0, type), w = as_type(layer_weight, type), t = as_type(parts.time, type);
    at::Tensor out = at::empty({w.size(0)}, b.options());
    T* o = out.data_ptr<T>();
    const T *bp = b.data_ptr<T>(), *wp = w.data_ptr<T>(), *tp = t.data_ptr<T>();
    for (int64_t r = 0; r < w.size(0); ++r) {
        T sum = T(0);
        for (int64_t j = parts.ex; j < parts.encoded; ++j) {
            sum += wp[r * w.stride(0) + j * w.stride(1)] * tp[(j - parts.ex) * t.stride(1)];
        }
        o[r] = sum + bp[r * b.stride(0)];
    }
    return out;
}

// A whole layer's weight gradient [O, columns] from its parts: x's columns (dx_part [O, ex]), the time
// row's (db t, the bias gradient times the row), then the hidden input's (dh [O, K], or none).
template <typename T>
at::Tensor whole_gradient(const at::Tensor& dx_part, const at::Tensor& db, const at::Tensor& dh, const Parts& parts,
                          int64_t columns) {
    const int64_t o = dx_part.size(0), k = dh.defined() ? dh.size(1) : 0;
    at::Tensor out = at::empty({o, columns}, dx_part.options());
    const at::Tensor t = as_type(parts.time, dx_part.scalar_type());
    T* w = out.data_ptr<T>();
    const T *xp = dx_part.data_ptr<T>(), *bp = db.data_ptr<T>(), *tp = t.data_ptr<T>();
    for (int64_t r = 0; r < o; ++r) {
        T* row = w + r * columns;
        std::copy(xp + r * parts.ex, xp + (r + 1) * parts.ex, row);
        for (int64_t j = parts.ex; j < parts.encoded; ++j) {
            row[j] = bp[r] * tp[(j - parts.ex) * t.stride(1)];
        }
        if (k > 0) {
            const T* hp = dh.data_ptr<T>() + r * k;
            std::copy(hp, hp + k, row + parts.encoded);
        }
    }
    return out;
}

Parts make_parts(const c10::optional<at::Tensor>& time_row, int64_t ex, int64_t encoded) {
    Parts parts;
    if (time_row.has_value()) {
        TORCH_CHECK(time_row->dim() == 2 && time_row->size(0) == 1 && time_row->size(1) == encoded - ex,
                    "fused MLP: the time row must be [1, encoded - x's columns]");
        parts.time = *time_row;
        parts.ex = ex;
        parts.encoded = encoded;
    }
    return parts;
}

// [the outputs (one per group), then with ``save`` (a gradient to come) x padded (bf16 with ``bf16``)
// and per layer what the backward reads, padded: z for SiLU (h is recomputed from it) and for the
// linear last layer, h for ReLU]. The last layer's outputs in ``groups`` of consecutive columns (each
// its own tensor, contiguous), those from ``scaled_from`` on (>= 0) as r |r| / scale (f_trd's rates,
// dynamics.py's scale_acceleration).
std::vector<at::Tensor> mlp_forward(
    const at::Tensor& x,
    std::vector<at::Tensor> weights,
    std::vector<at::Tensor> biases,
    c10::optional<at::Tensor> skip_weight,
    int64_t skip_layer,
    int64_t activation,
    bool last_activation,
    bool bf16,
    const c10::optional<at::Tensor>& time_row,
    int64_t encoded,
    std::vector<int64_t> groups,
    int64_t scaled_from,
    double scale,
    bool save) {
    const int64_t layers = int64_t(weights.size());
    TORCH_CHECK(layers > 0 && int64_t(biases.size()) == layers, "mlp_forward: one bias per weight");
    TORCH_CHECK(!bf16 || (BF16_PRODUCTS && x.scalar_type() == at::kFloat),
                "mlp_forward: bf16 products need float32 inputs and an AVX512-BF16 build");
    TORCH_CHECK(activation == RELU || activation == SILU, "mlp_forward: unknown activation");
    TORCH_CHECK(x.dim() == 2 && (x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble),
                "mlp_forward: x must be [N, E] float32 or float64");
    TORCH_CHECK(scaled_from < 0 || !last_activation, "mlp_forward: scaled outputs need a linear last layer");
    const Parts parts = make_parts(time_row, x.size(1), encoded);
    const std::vector<at::Tensor> whole = weights;
    take_parts(parts, weights, skip_weight, skip_layer);
    TORCH_CHECK(skip_layer < 0 || skip_weight.has_value(), "mlp_forward: the skip layer needs its weight");
    const int64_t n = x.size(0), outputs = weights.back().size(0);
    int64_t grouped = 0;
    for (const int64_t g : groups) {
        TORCH_CHECK(g > 0, "mlp_forward: an output group has no columns");
        grouped += g;
    }
    TORCH_CHECK(grouped == outputs, "mlp_forward: the output groups do not cover the last layer");
    std::vector<at::Tensor> saved(groups.size());
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "mlp_forward", [&] {
        if (parts.defined()) {
            biases[0] = fold_time<scalar_t>(biases[0], whole[0], parts);
            if (skip_layer >= 0) {
                biases[skip_layer] = fold_time<scalar_t>(biases[skip_layer], whole[skip_layer], parts);
            }
        }
        // x [N padded to PAD rows, E padded], each chunk's rows packed by its thread: as bf16 only with
        // bf16 products (their operand, and the backward's; a float copy was a pass over memory for nothing)
        // (contiguous for pack_rows_bf16 in a bf16 call: the fields' inputs already are)
        const at::Tensor xt0 = as_type(x, c10::CppTypeToScalarType<scalar_t>::value);
        const at::Tensor xt = bf16 ? xt0.contiguous() : xt0;
        const int64_t rows = padded(n), ke = padded(x.size(1)), last = layers - 1;
        const auto options = x.options().dtype(xt.scalar_type());
        at::Tensor input, input_bf16;
        if (bf16) {
            input_bf16 = at::empty({rows, ke}, x.options().dtype(at::kBFloat16));
            std::fill(bf16_data(input_bf16) + n * ke, bf16_data(input_bf16) + rows * ke, uint16_t(0));
            saved.push_back(input_bf16);
        } else {
            input = at::empty({rows, ke}, options);
            std::fill(input.data_ptr<scalar_t>() + n * ke, input.data_ptr<scalar_t>() + rows * ke, scalar_t(0));
            saved.push_back(input);
        }
        // the layers' operands, packed once; what the backward reads (``kept``): z for SiLU and the linear
        // last layer, h for ReLU; without a gradient to come only the last layer's
        std::vector<PackedB> packed(layers);
        std::vector<at::Tensor> bias(layers), kept(layers);
        std::vector<int64_t> acts(layers);
        int64_t widest = 0;
        for (int64_t i = 0; i < layers; ++i) {
            TORCH_CHECK(weights[i].size(1) == (i == 0 ? x.size(1) : weights[i - 1].size(0)),
                        "mlp_forward: layer ", i, " does not take the previous layer's width");
            packed[i] = pack_b<scalar_t>(weights[i], true, -1, bf16);
            bias[i] = pad_vector<scalar_t>(biases[i]);
            acts[i] = activates(i, layers, last_activation) ? activation : NONE;
            const int64_t m = padded(weights[i].size(0));
            widest = std::max(widest, m);
            if (save || i == last) {
                kept[i] = at::empty({rows, m}, options);
                TORCH_CHECK(reinterpret_cast<uintptr_t>(kept[i].data_ptr()) % 64 == 0,
                            "mlp_forward: a kept tensor is not 64-byte aligned (store_kept)");
                std::fill(kept[i].data_ptr<scalar_t>() + n * m, kept[i].data_ptr<scalar_t>() + rows * m, scalar_t(0));
            }
        }
        const PackedB packed_skip = skip_layer >= 0 ? pack_b<scalar_t>(*skip_weight, true, -1, bf16) : PackedB{};
        const int64_t m_last = kept[last].size(1);
        at::Tensor out_h;  // a SiLU last layer's output (its z is kept)
        if (acts[last] == SILU) {
            out_h = at::zeros({rows, m_last}, options);
        }
        std::vector<at::Tensor> outs(groups.size());
        for (size_t g = 0; g < groups.size(); ++g) {
            outs[g] = at::empty({n, groups[g]}, options);
        }
        // Chunks of CHUNK_ROWS points, each carried through every layer by one thread: a layer's h in the
        // thread's own buffers for the next (cached, not a pass over all the points a layer), and the
        // same chunks as the backward's (each thread then finds its rows in its own cache).
        const int64_t chunks = chunks_of(n);
        at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
            const int64_t slot = CHUNK_ROWS * widest;
            std::unique_ptr<scalar_t[]> scratch(new scalar_t[2 * slot]);
            std::unique_ptr<uint16_t[]> scratch16(bf16 ? new uint16_t[2 * slot] : nullptr);
            for (int64_t c = c0; c < c1; ++c) {
                const int64_t r0 = c * CHUNK_ROWS, cr = std::min(n, r0 + CHUNK_ROWS) - r0;
                if (bf16) {  // (rounded as the products' other operands)
                    pack_rows_bf16(xt, r0, r0 + cr, bf16_data(input_bf16), ke);
                } else {
                    pack_rows<scalar_t>(xt, r0, r0 + cr, input.data_ptr<scalar_t>(), ke);
                }
                const Operand<scalar_t> x_rows{nullptr, bf16 ? nullptr : input.data_ptr<scalar_t>() + r0 * ke,
                                               bf16 ? bf16_data(input_bf16) + r0 * ke : nullptr, ke};
                Operand<scalar_t> cur = x_rows;
                for (int64_t i = 0, turn = 0; i < layers; ++i, turn ^= 1) {
                    const int64_t m = packed[i].b.size(1);
                    scalar_t* keep = kept[i].defined() ? kept[i].data_ptr<scalar_t>() + r0 * m : nullptr;
                    // (a hidden layer's h in float only where the next product reads floats)
                    scalar_t* h = i < last ? (bf16 ? nullptr : scratch.get() + turn * slot)
                                           : (out_h.defined() ? out_h.data_ptr<scalar_t>() + r0 * m : nullptr);
                    uint16_t* h16 = bf16 && i < last ? scratch16.get() + turn * slot : nullptr;
                    cur.b = &packed[i];
                    with_activation<scalar_t>(acts[i], [&](auto a) {
                        const ForwardStore<scalar_t, decltype(a)::value> store{keep, h, m, h16};
                        if (i == skip_layer) {  // (layer i also takes x S^T)
                            Operand<scalar_t> skip = x_rows;
                            skip.b = &packed_skip;
                            chunk_product<scalar_t>({cur, skip}, bias[i].data_ptr<scalar_t>(), cr, store);
                        } else {
                            chunk_product<scalar_t>({cur}, bias[i].data_ptr<scalar_t>(), cr, store);
                        }
                    });
                    cur = {nullptr, h, h16, m};
                }
                write_groups<scalar_t>(out_h.defined() ? out_h : kept[last], r0, r0 + cr, outs, scaled_from, scale);
            }
#if defined(__AVX512F__)
            _mm_sfence();  // (the streaming stores seen by every thread after the loop)
#endif
        });
        std::copy(outs.begin(), outs.end(), saved.begin());
        if (save) {
            saved.insert(saved.end(), kept.begin(), kept.end());
        }
    });
    return saved;
}

// [d weights (L), d biases (L), d skip weight, d x] (the last two empty when not asked for; with a time
// row the first and the skip layer's weight gradients are whole and the skip weight's is empty).
// ``grads_out``: the gradients of mlp_forward's outputs (its groups, scaled or not, in order).
std::vector<at::Tensor> mlp_backward(
    std::vector<at::Tensor> grads_out,
    std::vector<at::Tensor> saved,
    std::vector<at::Tensor> weights,
    c10::optional<at::Tensor> skip_weight,
    int64_t skip_layer,
    int64_t activation,
    bool last_activation,
    int64_t stop_from,
    bool wants_x,
    bool bf16,
    const c10::optional<at::Tensor>& time_row,
    int64_t encoded,
    int64_t scaled_from,
    double scale) {
    const int64_t layers = int64_t(weights.size());
    TORCH_CHECK(int64_t(saved.size()) == 1 + layers, "mlp_backward: saved tensors do not match");
    TORCH_CHECK(!grads_out.empty(), "mlp_backward: no output gradients");
    const at::Tensor& input = saved[0];  // (x padded: bf16 with bf16 products, mlp_forward's)
    TORCH_CHECK(!bf16 || (BF16_PRODUCTS && input.scalar_type() == at::kBFloat16 && saved[1].scalar_type() == at::kFloat),
                "mlp_backward: bf16 products need a bf16 call's saved tensors and an AVX512-BF16 build");
    const Parts parts = make_parts(time_row, encoded - (time_row.has_value() ? time_row->size(1) : 0), encoded);
    const std::vector<at::Tensor> whole = weights;
    take_parts(parts, weights, skip_weight, skip_layer);
    const auto type = saved[1].scalar_type();
    const auto options = saved[1].options();
    const int64_t n = grads_out[0].size(0), rows = input.size(0);
    std::vector<at::Tensor> grads(2 * layers + 2, at::empty({0}, options));
    at::Tensor dx;
    AT_DISPATCH_FLOATING_TYPES(type, "mlp_backward", [&] {
        // dz of the last layer: the incoming gradients, padded (the scaled outputs' times 2 |r| / scale),
        // times its activation's derivative
        const int64_t last = layers - 1;
        const int64_t m_last = saved[1 + last].size(1);
        at::Tensor dz = at::empty({rows, m_last}, options);
        {
            scalar_t* p = dz.data_ptr<scalar_t>();
            const scalar_t* raw = saved[1 + last].data_ptr<scalar_t>();
            const scalar_t twice = scalar_t(2) / scalar_t(scale);
            std::fill(p, p + rows * m_last, scalar_t(0));
            int64_t c0 = 0;
            for (const at::Tensor& g0 : grads_out) {
                const at::Tensor g = as_type(g0, type);
                const scalar_t* gp = g.data_ptr<scalar_t>();
                const int64_t o = g.size(1), s0 = g.stride(0), s1 = g.stride(1);
                TORCH_CHECK(g.size(0) == n && c0 + o <= m_last, "mlp_backward: an output gradient's shape");
                for (int64_t r = 0; r < n; ++r) {
                    for (int64_t c = 0; c < o; ++c) {
                        const scalar_t v = gp[r * s0 + c * s1];
                        const int64_t at = r * m_last + c0 + c;
                        p[at] = scaled_from >= 0 && c0 + c >= scaled_from ? v * (twice * std::abs(raw[at])) : v;
                    }
                }
                c0 += o;
            }
        }
        if (activates(last, layers, last_activation)) {
            const at::Tensor& s = saved[1 + last];  // (z, or h for ReLU)
            with_activation<scalar_t>(activation, [&](auto a) {
                constexpr int64_t L = LANES<scalar_t>;
                scalar_t* p = dz.data_ptr<scalar_t>();
                const scalar_t* sp = s.data_ptr<scalar_t>();
                for (int64_t e = 0; e < n * m_last; e += L) {
                    storev(p + e, derivative<scalar_t, decltype(a)::value>(loadv(p + e), loadv(sp + e)));
                }
            });
        }
        // Chunks of CHUNK_ROWS points, each carried back through every layer by one thread: its weight
        // gradients' partial sums, then its rows of dz_{i-1} = (dz_i W_i) act'(z_{i-1}) in the thread's
        // own buffers (cached, not a pass over all the points per product). The same arithmetic per
        // row and per chunk as layer by layer, so the same sums.
        const int64_t chunks = chunks_of(n);
        std::vector<int64_t> ms(layers), ks(layers), offsets(layers + 1);
        int64_t total = 0, widest = m_last;
        for (int64_t i = 0; i < layers; ++i) {
            ms[i] = saved[1 + i].size(1);
            ks[i] = saved[i].size(1);  // (x, or the previous layer's z or h)
            widest = std::max(widest, ks[i]);
            offsets[i] = total;
            total += chunks * (ms[i] * ks[i] + ms[i]);
        }
        const int64_t ke = input.size(1);
        offsets[layers] = total;
        if (skip_layer >= 0) {
            total += chunks * (ms[skip_layer] * ke + ms[skip_layer]);
        }
        std::unique_ptr<scalar_t[]> partial(new scalar_t[total]);  // (the rows summed are written first)
        std::vector<PackedB> packed(layers);  // (the weights' rows from stop_from on: no input gradient)
        for (int64_t i = last; i >= 1; --i) {
            packed[i] = pack_b<scalar_t>(weights[i], false, i == last ? stop_from : -1, bf16);
        }
        PackedB packed_x, packed_skip;
        if (wants_x) {
            dx = at::zeros({rows, ke}, options);
            packed_x = pack_b<scalar_t>(weights[0], false, last == 0 ? stop_from : -1, bf16);
            if (skip_layer >= 0) {
                packed_skip = pack_b<scalar_t>(*skip_weight, false, skip_layer == last ? stop_from : -1, bf16);
            }
        }
        const scalar_t* dz_last = dz.data_ptr<scalar_t>();
        at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
            const int64_t slot = CHUNK_ROWS * widest;
            std::unique_ptr<scalar_t[]> scratch(new scalar_t[2 * slot]);
            std::unique_ptr<uint16_t[]> scratch16(bf16 ? new uint16_t[3 * slot] : nullptr);
            std::unique_ptr<uint32_t[]> pairs(bf16 ? new uint32_t[slot] : nullptr);  // (row_pairs' of dz, of h or x)
            // a SiLU layer's h and sigmoid, from its kept z (the forward keeps z only)
            std::unique_ptr<scalar_t[]> recomputed(activation == SILU && layers > 1 ? new scalar_t[2 * slot] : nullptr);
            for (int64_t c = c0; c < c1; ++c) {
                const int64_t r0 = c * CHUNK_ROWS, cr = std::min(n, r0 + CHUNK_ROWS) - r0;
                const scalar_t* cur = dz_last + r0 * m_last;
                const uint16_t* cur16 = nullptr;
                if (bf16) {  // (the input gradients' operand: the last layer's dz rows as bf16)
                    for (int64_t e = 0; e < cr * m_last; e += LANES<scalar_t>) {
                        store_copy<scalar_t>(scratch16.get() + 2 * slot, e, loadv(cur + e));
                    }
                    cur16 = scratch16.get() + 2 * slot;
                }
                for (int64_t i = last, turn = 0; i >= 0; --i, turn ^= 1) {
                    const int64_t m = ms[i], k = ks[i];
                    // h_{i-1} (padded): x, kept (ReLU), or z sigmoid(z) from the kept z (SiLU), as the forward
                    // (x as bf16 rows with bf16 products: x16)
                    const scalar_t* in = bf16 && i == 0 ? nullptr : saved[i].data_ptr<scalar_t>() + r0 * k;
                    const scalar_t* x = bf16 ? nullptr : input.data_ptr<scalar_t>() + r0 * ke;
                    const uint16_t* x16 = bf16 ? bf16_data(input) + r0 * ke : nullptr;
                    scalar_t* sig = recomputed.get();
                    if (i > 0 && activation == SILU && bf16 && silu_pairs<scalar_t>(in, cr, k, sig, pairs.get() + slot / 2)) {
                        in = nullptr;  // (its pairs made)
                    } else if (i > 0 && activation == SILU) {
                        scalar_t* h = recomputed.get() + slot;
                        for (int64_t e = 0; e < cr * k; e += LANES<scalar_t>) {
                            if (e + AHEAD * k < cr * k) {  // (prefetch_rows': z from memory)
                                __builtin_prefetch(in + e + AHEAD * k, 0, 3);
                            }
                            const typename VT<scalar_t>::v z = loadv(in + e), sz = sigmoid<scalar_t>(z);
                            storev(sig + e, sz);
                            storev(h + e, z * sz);
                        }
                        in = h;
                    }
                    scalar_t* pw = partial.get() + offsets[i] + c * (m * k + m);
                    // (the skip weight's: the same dz with x; its bias is the layer's)
                    scalar_t* ps = i == skip_layer ? partial.get() + offsets[layers] + c * (m * ke + m) : nullptr;
                    layer_partials<scalar_t>(cur, m, in, k, x, ke, cr, pw,
                                             weights[i].size(0), ps, ps ? skip_weight->size(0) : 0, pairs.get(),
                                             slot / 2, x16, bf16 && i == 0);
                    // d x += dz_i W_i (the first layer) and dz_i S (the skip layer; both where that is the first)
                    for (int64_t part = 0; wants_x && part < 2; ++part) {
                        if (part == 0 ? i != 0 : i != skip_layer) {
                            continue;
                        }
                        scalar_t* dxp = dx.data_ptr<scalar_t>() + r0 * ke;
                        const Operand<scalar_t> dz_rows{part == 0 ? &packed_x : &packed_skip, cur, cur16, m};
                        chunk_product<scalar_t>({dz_rows}, nullptr, cr,
                                                [&](int64_t r, int64_t col, typename VT<scalar_t>::v v) {
                                                    storev(dxp + r * ke + col, loadv(dxp + r * ke + col) + v);
                                                });
                    }
                    if (i == 0) {
                        break;
                    }
                    scalar_t* next = scratch.get() + turn * slot;
                    uint16_t* next16 = bf16 ? scratch16.get() + turn * slot : nullptr;
                    const scalar_t* z = saved[i].data_ptr<scalar_t>() + r0 * k;  // (z, or h for ReLU)
                    with_activation<scalar_t>(activation, [&](auto a) {
                        chunk_product<scalar_t>({{&packed[i], cur, cur16, m}}, nullptr, cr,
                                                BackwardStore<scalar_t, decltype(a)::value>{next, z, sig, k, next16});
                    });
                    cur = next;
                    cur16 = next16;
                }
            }
        });
        for (int64_t i = last; i >= 0; --i) {
            const int64_t o_real = weights[i].size(0), k_real = weights[i].size(1);
            at::Tensor dw = at::empty({o_real, k_real}, options);
            at::Tensor db = at::empty({o_real}, options);
            reduce_partials<scalar_t>(partial.get() + offsets[i], chunks, ms[i], ks[i], dw.data_ptr<scalar_t>(),
                                      db.data_ptr<scalar_t>(), o_real, k_real);
            at::Tensor ds;
            if (i == skip_layer) {
                ds = at::empty({skip_weight->size(0), skip_weight->size(1)}, options);
                reduce_partials<scalar_t>(partial.get() + offsets[layers], chunks, ms[i], ke, ds.data_ptr<scalar_t>(),
                                          nullptr, ds.size(0), ds.size(1));
            }
            if (parts.defined() && (i == 0 || i == skip_layer)) {  // whole: [x's | the time row's | hidden]
                dw = i == 0 ? whole_gradient<scalar_t>(dw, db, at::Tensor(), parts, parts.encoded)
                            : whole_gradient<scalar_t>(ds, db, dw, parts, whole[i].size(1));
            } else if (i == skip_layer) {
                grads[2 * layers] = as_type(ds, skip_weight->scalar_type());
            }
            grads[i] = as_type(dw, whole[i].scalar_type());
            grads[layers + i] = as_type(db, whole[i].scalar_type());
        }
    });
    if (wants_x) {
        grads[2 * layers + 1] = dx.narrow(0, 0, n).narrow(1, 0, weights[0].size(1)).contiguous();
    }
    return grads;
}

// ----- the fields' positional encoding ----------------------------------------------------------
// [u, sin(2^0 u), cos(2^0 u), ..., sin(2^(L-1) u), cos(2^(L-1) u)] of u [N, D] (models/encoding.py's
// layout), one op instead of ATen's ~8 with their [N, L, D] temporaries. The angles 2^k u are exact;
// float sin and cos come from one reduction by pi/2 (three-part Cody-Waite constants, exact for
// |x| < 2^15, std::sin beyond) and Cephes' minimax polynomials on [-pi/4, pi/4]: within ~2e-7 of the correctly
// rounded values, vectorised over the flattened inputs (std::sin per element is ~20x slower).
inline void sincos_v(VT<float>::v x, VT<float>::v& s, VT<float>::v& c) {
    typedef int32_t vi __attribute__((vector_size(VBYTES)));
    const VT<float>::v j = (x * 0.636619772f + 12582912.0f) - 12582912.0f;  // round(x 2 / pi)
    const VT<float>::v r = ((x - j * 1.5703125f) - j * 4.837512969970703125e-4f) - j * 7.54978995489188216e-8f;
    const VT<float>::v z = r * r;
    const VT<float>::v sr = r + r * z * (-1.6666654611e-1f + z * (8.3321608736e-3f + z * -1.9515295891e-4f));
    const VT<float>::v cr =
        1.0f - 0.5f * z + z * z * (4.166664568298827e-2f + z * (-1.388731625493765e-3f + z * 2.443315711809948e-5f));
    const vi q = __builtin_convertvector(j, vi);
    const vi odd = (q & 1) != 0;
    const VT<float>::v sv = odd ? cr : sr, cv = odd ? sr : cr;
    s = (q & 2) != 0 ? -sv : sv;
    c = ((q + 1) & 2) != 0 ? -cv : cv;
}

at::Tensor positional_encoding(const at::Tensor& u0, int64_t frequencies, bool include_input) {
    TORCH_CHECK(u0.dim() == 2 && u0.scalar_type() == at::kFloat && u0.device().is_cpu(),
                "positional_encoding: u must be a float32 CPU tensor [N, D]");
    TORCH_CHECK(frequencies >= 0 && frequencies < 24, "positional_encoding: frequencies must be in [0, 24)");
    const at::Tensor u = u0.contiguous();
    const int64_t n = u.size(0), d = u.size(1), first = include_input ? d : 0;
    const int64_t e = first + 2 * frequencies * d;
    at::Tensor out = at::empty({n, e}, u.options());
    const float* up = u.data_ptr<float>();
    float* op = out.data_ptr<float>();
    constexpr int64_t L = LANES<float>;
    // flattened inputs j = row d + channel, a block of L at a time (the last one partly)
    const int64_t blocks = (n * d + L - 1) / L;
    at::parallel_for(0, blocks, 2048 / L, [&](int64_t b0, int64_t b1) {
        for (int64_t b = b0; b < b1; ++b) {
            const int64_t j0 = b * L, count = std::min<int64_t>(L, n * d - j0);
            float lane[L] = {};
            std::memcpy(lane, up + j0, count * sizeof(float));
            int64_t base[L];  // where input j0 + l's first output goes (one division a block, not a lane)
            for (int64_t l = 0, row = j0 / d, channel = j0 % d; l < count; ++l) {
                base[l] = row * e + channel;
                if (include_input) {
                    op[base[l]] = lane[l];
                }
                if (++channel == d) {
                    channel = 0, ++row;
                }
            }
            const VT<float>::v x = loadv(lane);
            float scale = 1.0f;
            float largest = 0.0f;
            for (int64_t l = 0; l < count; ++l) {
                largest = std::max(largest, std::fabs(lane[l]));
            }
            for (int64_t k = 0; k < frequencies; ++k, scale *= 2.0f) {
                VT<float>::v s, c;
                if (largest * scale < 32768.0f) {
                    sincos_v(x * scale, s, c);
                } else {  // beyond the reduction's exact range (never at the fields' scene sizes)
                    for (int64_t l = 0; l < L; ++l) {
                        s[l] = std::sin(lane[l] * scale);
                        c[l] = std::cos(lane[l] * scale);
                    }
                }
                const int64_t at_sin = first + 2 * k * d, at_cos = at_sin + d;
                for (int64_t l = 0; l < count; ++l) {
                    op[base[l] + at_sin] = s[l];
                    op[base[l] + at_cos] = c[l];
                }
            }
        }
    });
    return out;
}

// ----- f_defo's output applied to the Gaussians -------------------------------------------------
// models/deformation.py's ``apply_deformation`` on rows ``rows`` of the canonical Gaussians (all rows
// without it), the other rows kept: x = x0 + dx, q = normalize(dq) o q0 (Hamilton product),
// log_s = log_s0 + dlog_s. One op forward and one backward instead of ~25 ATen ops and their autograd
// nodes (the gathers of the rows, the quaternion's component products, the index copies back).
// M: the rows the field moved.
template <typename T>
inline void hamilton(const T* a, const T* b, T* out) {
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

constexpr double NORM_EPS = 1e-12;  // physics/so3.py quat_normalize's clamp

template <typename T>
inline T unit(const T* q, T* p) {  // p = q / max(|q|, eps); returns that divisor
    const T n = std::max<T>(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), T(NORM_EPS));
    for (int c = 0; c < 4; ++c) {
        p[c] = q[c] / n;
    }
    return n;
}

void check_rows(const c10::optional<at::Tensor>& rows, int64_t n, int64_t m) {
    if (rows) {
        TORCH_CHECK(rows->dim() == 1 && rows->scalar_type() == at::kLong && rows->size(0) == m,
                    "deform: rows must be an int64 tensor of the moved rows' count");
    } else {
        TORCH_CHECK(m == n, "deform: without rows, every row moves");
    }
}

std::vector<at::Tensor> deform_forward(const at::Tensor& x0, const at::Tensor& q0, const at::Tensor& s0,
                                       const c10::optional<at::Tensor>& rows, const at::Tensor& dx,
                                       const at::Tensor& dq, const at::Tensor& ds) {
    const int64_t n = x0.size(0), m = dx.size(0);
    check_rows(rows, n, m);
    at::Tensor x = x0.contiguous().clone(), q = q0.contiguous().clone(), s = s0.contiguous().clone();
    const at::Tensor dxc = dx.contiguous(), dqc = dq.contiguous(), dsc = ds.contiguous();
    const at::Tensor index = rows ? rows->contiguous() : at::Tensor();
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "deform_forward", [&] {
        scalar_t *xp = x.data_ptr<scalar_t>(), *qp = q.data_ptr<scalar_t>(), *sp = s.data_ptr<scalar_t>();
        const scalar_t *dxp = dxc.data_ptr<scalar_t>(), *dqp = dqc.data_ptr<scalar_t>(), *dsp = dsc.data_ptr<scalar_t>();
        const int64_t* rp = rows ? index.data_ptr<int64_t>() : nullptr;
        at::parallel_for(0, m, 2048, [&](int64_t i0, int64_t i1) {
            for (int64_t i = i0; i < i1; ++i) {
                const int64_t r = rp ? rp[i] : i;
                TORCH_CHECK(r >= 0 && r < n, "deform: row index out of range");
                scalar_t p[4], q_old[4];
                unit(dqp + 4 * i, p);
                std::copy(qp + 4 * r, qp + 4 * r + 4, q_old);
                hamilton(p, q_old, qp + 4 * r);
                for (int c = 0; c < 3; ++c) {
                    xp[3 * r + c] += dxp[3 * i + c];
                    sp[3 * r + c] += dsp[3 * i + c];
                }
            }
        });
    });
    return {x, q, s};
}

// Gradients (g0 for x0 and log_s0 are the incoming ones, returned as they are):
// q0: p* o gq on the moved rows; dq: (gp - p (p . gp)) / |dq| with gp = gq o q0*; dx, dlog_s: the rows.
std::vector<at::Tensor> deform_backward(const at::Tensor& gq0_in, const at::Tensor& gx0, const at::Tensor& gs0,
                                        const at::Tensor& q0_in, const c10::optional<at::Tensor>& rows,
                                        const at::Tensor& dq_in) {
    const int64_t n = q0_in.size(0), m = dq_in.size(0);
    check_rows(rows, n, m);
    const at::Tensor gq = gq0_in.contiguous(), gx = gx0.contiguous(), gs = gs0.contiguous();
    const at::Tensor q0 = q0_in.contiguous(), dq = dq_in.contiguous();
    const at::Tensor index = rows ? rows->contiguous() : at::Tensor();
    at::Tensor gq_canonical = gq.clone();
    at::Tensor gdx = at::empty({m, 3}, gx.options()), gdq = at::empty({m, 4}, gq.options());
    at::Tensor gds = at::empty({m, 3}, gs.options());
    AT_DISPATCH_FLOATING_TYPES(gq.scalar_type(), "deform_backward", [&] {
        const scalar_t *gqp = gq.data_ptr<scalar_t>(), *gxp = gx.data_ptr<scalar_t>(), *gsp = gs.data_ptr<scalar_t>();
        const scalar_t *q0p = q0.data_ptr<scalar_t>(), *dqp = dq.data_ptr<scalar_t>();
        scalar_t *gcp = gq_canonical.data_ptr<scalar_t>(), *gdxp = gdx.data_ptr<scalar_t>();
        scalar_t *gdqp = gdq.data_ptr<scalar_t>(), *gdsp = gds.data_ptr<scalar_t>();
        const int64_t* rp = rows ? index.data_ptr<int64_t>() : nullptr;
        at::parallel_for(0, m, 2048, [&](int64_t i0, int64_t i1) {
            for (int64_t i = i0; i < i1; ++i) {
                const int64_t r = rp ? rp[i] : i;
                scalar_t p[4], conj[4], gp[4];
                const scalar_t norm = unit(dqp + 4 * i, p);
                const scalar_t* g = gqp + 4 * r;
                const scalar_t p_conj[4] = {p[0], -p[1], -p[2], -p[3]};
                hamilton(p_conj, g, gcp + 4 * r);
                const scalar_t* q = q0p + 4 * r;
                conj[0] = q[0], conj[1] = -q[1], conj[2] = -q[2], conj[3] = -q[3];
                hamilton(g, conj, gp);
                const bool clamped = norm <= scalar_t(NORM_EPS);  // (the clamp passes no norm gradient)
                const scalar_t along = clamped ? scalar_t(0) : p[0] * gp[0] + p[1] * gp[1] + p[2] * gp[2] + p[3] * gp[3];
                for (int c = 0; c < 4; ++c) {
                    gdqp[4 * i + c] = (gp[c] - p[c] * along) / norm;
                }
                for (int c = 0; c < 3; ++c) {
                    gdxp[3 * i + c] = gxp[3 * r + c];
                    gdsp[3 * i + c] = gsp[3 * r + c];
                }
            }
        });
    });
    return {gq_canonical, gdx, gdq, gds};
}

// The vector width the kernels were built for, in bytes (64: AVX-512, 32: AVX2, 16: SSE or NEON).
int64_t vector_bytes() { return VBYTES; }

// Whether mlp_forward and mlp_backward take ``bf16`` (built for AVX512-BF16).
bool bf16_products() { return BF16_PRODUCTS; }

}  // namespace

TORCH_LIBRARY(tracegs_mlp_cpu, m) {
    m.def("vector_bytes", &vector_bytes);
    m.def("bf16_products", &bf16_products);
    m.def("mlp_forward", &mlp_forward);
    m.def("mlp_backward", &mlp_backward);
    m.def("positional_encoding", &positional_encoding);
    m.def("deform_forward", &deform_forward);
    m.def("deform_backward", &deform_backward);
}
