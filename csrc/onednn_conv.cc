// The three passes of a strided 2-D convolution on oneDNN, as XLA FFI handlers.
//
// Layouts are JAX's: frames NHWC, kernels HWIO (oneDNN's dims O, I, KH, KW with format tag
// hwio). oneDNN picks its own kernel layout ("any"); the kernel is reordered into it, or the
// kernel gradient out of it, inside the call. Every pass takes the stride and the leading
// padding as attributes; the trailing padding follows from the shapes, so one convolution
// serves a strided convolution (its output size rounded down) and, as its input gradient, a
// PyTorch-style transposed convolution.
//
// Primitives are cached per thread by pass and shape: building one costs tens of microseconds,
// running a small one about as much.
//
// Every operand may carry a leading axis of G configurations (a vmapped sweep: frames
// [G, n, h, w, c], kernels [G, k, k, c, o], biases [G, o]). The G convolutions then run side by
// side on XLA's own CPU threads, each on one thread (`ForConfigs`).

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include <omp.h>

#include "oneapi/dnnl/dnnl.hpp"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;
using dnnl::memory;

namespace {

int g_threads = 0;  // OpenMP threads of a large pass; 0: OpenMP's default
// A pass of fewer multiply-adds runs on one thread: waking an OpenMP team costs more than it
// saves there, and its threads compete with XLA's for the cores.
double g_parallel_macs = 1e7;

// kForwardSelu: the forward with the bias added and SELU applied inside the convolution
// (oneDNN post-ops: ELU with SELU's alpha, then a linear scale by SELU's lambda).
// kTransposedSelu: the input gradient as a transposed convolution's forward (oneDNN's
// deconvolution) with a bias [c] and SELU's post-ops.
enum Pass : int64_t { kForward = 0, kInputGrad = 1, kKernelGrad = 2, kForwardSelu = 3, kTransposedSelu = 4 };
constexpr float kSeluAlpha = 1.6732632423543772f;
constexpr float kSeluScale = 1.0507009873554805f;

dnnl::engine& Engine() {
  static dnnl::engine engine(dnnl::engine::kind::cpu, 0);
  return engine;
}

dnnl::stream& Stream() {
  thread_local dnnl::stream stream(Engine());
  return stream;
}

// One convolution's shapes: frames x [n, h, w, c], kernel [k, k, c, o], y [n, ho, wo, o].
struct Shapes {
  int64_t n, h, w, c, k, o, ho, wo, stride, pad;

  std::vector<int64_t> Key(int64_t pass, bool one_thread) const {
    return {pass, one_thread, n, h, w, c, k, o, ho, wo, stride, pad};
  }
  memory::desc X() const { return {{n, c, h, w}, memory::data_type::f32, memory::format_tag::nhwc}; }
  memory::desc Y() const { return {{n, o, ho, wo}, memory::data_type::f32, memory::format_tag::nhwc}; }
  memory::desc Kernel(memory::format_tag tag) const { return {{o, c, k, k}, memory::data_type::f32, tag}; }
  memory::desc Bias() const { return {{o}, memory::data_type::f32, memory::format_tag::x}; }
  // The kernel [k, k, c, o] (HWIO of the strided convolution) read as a deconvolution's
  // weights, whose output channels are c and input channels o.
  memory::desc Deconv() const { return {{c, o, k, k}, memory::data_type::f32, {o, 1, k * c * o, c * o}}; }
  memory::desc DeconvAny() const { return {{c, o, k, k}, memory::data_type::f32, memory::format_tag::any}; }
  memory::desc DeconvBias() const { return {{c}, memory::data_type::f32, memory::format_tag::x}; }
  // The kernel as the user holds it, for `pass`.
  memory::desc UserKernel(int64_t pass) const {
    return pass == 4 /* kTransposedSelu */ ? Deconv() : Kernel(memory::format_tag::hwio);
  }
  memory::dims Strides() const { return {stride, stride}; }
  memory::dims PadL() const { return {pad, pad}; }
  // The trailing padding that makes ho x wo windows end where the last one ends.
  memory::dims PadR() const { return {(ho - 1) * stride + k - h - pad, (wo - 1) * stride + k - w - pad}; }
  double Macs() const { return double(n) * ho * wo * o * c * k * k; }
};

struct Cached {
  int threads = 1;           // the OpenMP threads the primitives were made for
  dnnl::primitive conv;
  memory::desc kernel_desc;  // oneDNN's layout of the kernel (or its gradient)
  bool reorder = false;      // it differs from HWIO
  dnnl::reorder to_onednn;    // HWIO -> oneDNN's (forward, input gradient) or back (kernel gradient)
  memory kernel_buf;          // the kernel in oneDNN's layout, where it differs
};

dnnl::convolution_forward::primitive_desc ForwardDesc(const Shapes& s) {
  return dnnl::convolution_forward::primitive_desc(
      Engine(), dnnl::prop_kind::forward_training, dnnl::algorithm::convolution_direct, s.X(),
      s.Kernel(memory::format_tag::any), s.Y(), s.Strides(), s.PadL(), s.PadR());
}

// SELU as a primitive's post-ops: ELU with SELU's alpha, then a linear scale by its lambda.
dnnl::primitive_attr SeluAttr() {
  dnnl::post_ops ops;
  ops.append_eltwise(dnnl::algorithm::eltwise_elu, kSeluAlpha, 0.f);
  ops.append_eltwise(dnnl::algorithm::eltwise_linear, kSeluScale, 0.f);
  dnnl::primitive_attr attr;
  attr.set_post_ops(ops);
  return attr;
}

bool Parallel(double macs) { return macs >= g_parallel_macs && g_threads > 1; }

Cached Build(const Shapes& s, int64_t pass, bool one_thread) {
  Cached c;
  // oneDNN splits the work for the thread count it sees when a primitive is made.
  c.threads = !one_thread && Parallel(s.Macs()) ? g_threads : 1;
  omp_set_num_threads(c.threads);
  auto hwio = s.UserKernel(pass);
  auto fwd = ForwardDesc(s);
  if (pass == kForward) {
    c.conv = dnnl::convolution_forward(fwd);
    c.kernel_desc = fwd.weights_desc();
  } else if (pass == kForwardSelu) {
    dnnl::primitive_attr attr = SeluAttr();
    dnnl::convolution_forward::primitive_desc pd(
        Engine(), dnnl::prop_kind::forward_training, dnnl::algorithm::convolution_direct, s.X(),
        s.Kernel(memory::format_tag::any), s.Bias(), s.Y(), s.Strides(), s.PadL(), s.PadR(), attr);
    c.conv = dnnl::convolution_forward(pd);
    c.kernel_desc = pd.weights_desc();
  } else if (pass == kTransposedSelu) {
    dnnl::primitive_attr attr = SeluAttr();
    dnnl::deconvolution_forward::primitive_desc pd(
        Engine(), dnnl::prop_kind::forward_training, dnnl::algorithm::deconvolution_direct, s.Y(), s.DeconvAny(),
        s.DeconvBias(), s.X(), s.Strides(), s.PadL(), s.PadR(), attr);
    c.conv = dnnl::deconvolution_forward(pd);
    c.kernel_desc = pd.weights_desc();
  } else if (pass == kInputGrad) {
    dnnl::convolution_backward_data::primitive_desc pd(
        Engine(), dnnl::algorithm::convolution_direct, s.X(), s.Kernel(memory::format_tag::any), s.Y(),
        s.Strides(), s.PadL(), s.PadR(), fwd);
    c.conv = dnnl::convolution_backward_data(pd);
    c.kernel_desc = pd.weights_desc();
  } else {
    dnnl::convolution_backward_weights::primitive_desc pd(
        Engine(), dnnl::algorithm::convolution_direct, s.X(), s.Kernel(memory::format_tag::any), s.Y(),
        s.Strides(), s.PadL(), s.PadR(), fwd);
    c.conv = dnnl::convolution_backward_weights(pd);
    c.kernel_desc = pd.diff_weights_desc();
  }
  c.reorder = c.kernel_desc != hwio;
  if (c.reorder) {
    c.kernel_buf = memory(c.kernel_desc, Engine());
    c.to_onednn = pass == kKernelGrad
                      ? dnnl::reorder(dnnl::reorder::primitive_desc(Engine(), c.kernel_desc, Engine(), hwio))
                      : dnnl::reorder(dnnl::reorder::primitive_desc(Engine(), hwio, Engine(), c.kernel_desc));
  }
  return c;
}

// OpenMP's thread count is a setting of the calling thread, which may be the caller's own
// (another library on the same OpenMP runtime, as PyTorch's is): set for a pass, then put back.
class ThreadsFor {
 public:
  ThreadsFor() : before_(omp_get_max_threads()) {}
  void Use(int n) {
    if (omp_get_max_threads() != n) omp_set_num_threads(n);
  }
  ~ThreadsFor() { Use(before_); }

 private:
  int before_;
};

Cached& Lookup(const Shapes& s, int64_t pass, bool one_thread) {
  thread_local std::map<std::vector<int64_t>, Cached> cache;
  auto key = s.Key(pass, one_thread);
  auto it = cache.find(key);
  if (it == cache.end()) it = cache.emplace(key, Build(s, pass, one_thread)).first;
  return it->second;
}

// Threads of oneDNN passes running now. XLA runs independent operations side by side (a
// layer's input and kernel gradients, say), so two passes may each want every core.
std::atomic<int> g_busy{0};

// Counts `n` threads as busy for its lifetime.
class Busy {
 public:
  explicit Busy(int n) : n_(n) { g_busy += n; }
  ~Busy() { g_busy -= n_; }

 private:
  int n_;
};

// The configurations of one call, claimed one at a time by the threads that run them.
struct Claims {
  explicit Claims(int64_t n) : configs(n), errors(n, ffi::Error::Success()) {}
  const int64_t configs;
  std::atomic<int64_t> next{0}, done{0};
  std::vector<ffi::Error> errors;
};

// Runs `run(g, one_thread)` for the G configurations g; returns the first error. One
// configuration, or configurations each large enough for an OpenMP team of their own while
// fewer than the threads, run one after another with the team. Otherwise they run side by
// side, each on one thread: the calling thread and tasks on XLA's thread pool claim them one
// at a time (a task that starts after the last claim does nothing, so the call never waits
// for a thread busy elsewhere), on as many threads as no other pass holds.
template <typename F>
ffi::Error ForConfigs(ffi::ThreadPool pool, int64_t configs, double macs, F run) {
  if (configs == 1 || g_threads <= 1 || (Parallel(macs) && configs < g_threads)) {
    Busy busy(Parallel(macs) ? g_threads : 1);
    for (int64_t g = 0; g < configs; ++g) {
      ffi::Error e = run(g, false);
      if (e.failure()) return e;
    }
    return ffi::Error::Success();
  }
  int64_t threads = std::min<int64_t>({configs, g_threads, pool.num_threads() + 1});
  int team = int(std::max<int64_t>(1, std::min<int64_t>(threads, g_threads - g_busy.load())));
  Busy busy(team);
  auto claims = std::make_shared<Claims>(configs);
  auto work = [claims, run]() {
    for (int64_t g; (g = claims->next++) < claims->configs; ++claims->done) claims->errors[g] = run(g, true);
  };
  for (int i = 1; i < team; ++i) pool.Schedule([work] { work(); });
  work();
  while (claims->done.load() < configs) std::this_thread::yield();
  for (auto& e : claims->errors)
    if (e.failure()) return std::move(e);
  return ffi::Error::Success();
}

// Runs one pass. `x` and `y` are the frames and the windows' outputs (each the input or the
// result, by pass); `kernel` is the kernel (forward, input gradient) or its gradient.
ffi::Error Run(const Shapes& s, int64_t pass, float* x, float* kernel, float* y, float* bias = nullptr,
               bool one_thread = false) {
  ThreadsFor threads;
  try {
    Cached& c = Lookup(s, pass, one_thread);
    threads.Use(c.threads);
    auto& stream = Stream();
    memory xm(s.X(), Engine(), x), ym(s.Y(), Engine(), y);
    memory user(s.UserKernel(pass), Engine(), kernel);
    memory km = c.reorder ? c.kernel_buf : user;
    if (c.reorder && pass != kKernelGrad) {
      c.to_onednn.execute(stream, user, km);
    }
    if (pass == kForward) {
      c.conv.execute(stream, {{DNNL_ARG_SRC, xm}, {DNNL_ARG_WEIGHTS, km}, {DNNL_ARG_DST, ym}});
    } else if (pass == kForwardSelu) {
      memory bm(s.Bias(), Engine(), bias);
      c.conv.execute(stream, {{DNNL_ARG_SRC, xm}, {DNNL_ARG_WEIGHTS, km}, {DNNL_ARG_BIAS, bm}, {DNNL_ARG_DST, ym}});
    } else if (pass == kTransposedSelu) {
      memory bm(s.DeconvBias(), Engine(), bias);
      c.conv.execute(stream, {{DNNL_ARG_SRC, ym}, {DNNL_ARG_WEIGHTS, km}, {DNNL_ARG_BIAS, bm}, {DNNL_ARG_DST, xm}});
    } else if (pass == kInputGrad) {
      c.conv.execute(stream, {{DNNL_ARG_DIFF_SRC, xm}, {DNNL_ARG_WEIGHTS, km}, {DNNL_ARG_DIFF_DST, ym}});
    } else {
      c.conv.execute(stream, {{DNNL_ARG_SRC, xm}, {DNNL_ARG_DIFF_WEIGHTS, km}, {DNNL_ARG_DIFF_DST, ym}});
      if (c.reorder) c.to_onednn.execute(stream, km, user);
    }
    stream.wait();
  } catch (const dnnl::error& e) {
    return ffi::Error::Internal(std::string("oneDNN convolution failed: ") + e.what());
  }
  return ffi::Error::Success();
}

// The shapes of one configuration's convolution, and the configurations G, from frames x
// [(G,) n, h, w, c], a kernel [(G,) k, k, c, o] and outputs y [(G,) n, ho, wo, o]; false where
// the ranks or G disagree.
bool Unpack(ffi::AnyBuffer::Dimensions xd, ffi::AnyBuffer::Dimensions kd, ffi::AnyBuffer::Dimensions yd,
            int64_t stride, int64_t pad, Shapes* s, int64_t* configs) {
  size_t rank = xd.size();
  if ((rank != 4 && rank != 5) || kd.size() != rank || yd.size() != rank) return false;
  size_t i = rank - 4;
  *configs = i ? xd[0] : 1;
  if (i && (kd[0] != xd[0] || yd[0] != xd[0])) return false;
  *s = Shapes{xd[i], xd[i + 1], xd[i + 2], xd[i + 3], kd[i], kd[i + 3], yd[i + 1], yd[i + 2], stride, pad};
  return true;
}

constexpr const char* kShapeError = "conv: operands of rank 4 ([n, h, w, c]), or all of rank 5 with one leading "
                                    "axis of configurations, expected";

// Elements of one configuration's frames, kernel and outputs.
int64_t XSize(const Shapes& s) { return s.n * s.h * s.w * s.c; }
int64_t KSize(const Shapes& s) { return s.k * s.k * s.c * s.o; }
int64_t YSize(const Shapes& s) { return s.n * s.ho * s.wo * s.o; }

// Runs `pass` for every configuration: frames x, a kernel (or its gradient) k and the windows'
// outputs y, each the input or the result by pass, with their dimensions; with a bias per
// output channel of the pass (o for the strided forward, c for the transposed one) where given.
ffi::Error RunConfigs(ffi::ThreadPool pool, int64_t pass, ffi::AnyBuffer::Dimensions xd, float* xp,
                      ffi::AnyBuffer::Dimensions kd, float* kp, ffi::AnyBuffer::Dimensions yd, float* yp,
                      int64_t stride, int64_t pad, const ffi::Buffer<ffi::F32>* bias = nullptr) {
  Shapes s;
  int64_t g;
  if (!Unpack(xd, kd, yd, stride, pad, &s, &g)) return ffi::Error::InvalidArgument(kShapeError);
  float* bp = nullptr;
  int64_t channels = pass == kTransposedSelu ? s.c : s.o;
  if (bias != nullptr) {
    auto bd = bias->dimensions();
    if (bd.size() != xd.size() - 3 || bd.back() != channels || (bd.size() == 2 && bd[0] != g))
      return ffi::Error::InvalidArgument("conv: a bias per output channel (and configuration) expected");
    bp = const_cast<float*>(bias->typed_data());
  }
  return ForConfigs(pool, g, s.Macs(), [=](int64_t i, bool one) {
    return Run(s, pass, xp + i * XSize(s), kp + i * KSize(s), yp + i * YSize(s), bp ? bp + i * channels : nullptr,
               one);
  });
}

ffi::Error Forward(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> x, ffi::Buffer<ffi::F32> kernel,
                   ffi::ResultBuffer<ffi::F32> y, int64_t stride, int64_t pad) {
  return RunConfigs(pool, kForward, x.dimensions(), x.typed_data(), kernel.dimensions(), kernel.typed_data(),
                    y->dimensions(), y->typed_data(), stride, pad);
}

// SELU(forward + bias): x [(G,) n, h, w, c], the kernel and the bias [(G,) o] give y [(G,) n, ho, wo, o].
ffi::Error ForwardSelu(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> x, ffi::Buffer<ffi::F32> kernel,
                       ffi::Buffer<ffi::F32> bias, ffi::ResultBuffer<ffi::F32> y, int64_t stride, int64_t pad) {
  return RunConfigs(pool, kForwardSelu, x.dimensions(), x.typed_data(), kernel.dimensions(), kernel.typed_data(),
                    y->dimensions(), y->typed_data(), stride, pad, &bias);
}

// The input gradient: dy [(G,) n, ho, wo, o] and the kernel give dx [(G,) n, h, w, c].
ffi::Error InputGrad(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> dy, ffi::Buffer<ffi::F32> kernel,
                     ffi::ResultBuffer<ffi::F32> dx, int64_t stride, int64_t pad) {
  return RunConfigs(pool, kInputGrad, dx->dimensions(), dx->typed_data(), kernel.dimensions(), kernel.typed_data(),
                    dy.dimensions(), dy.typed_data(), stride, pad);
}

// SELU(input gradient + bias) as a transposed convolution's forward: dy [(G,) n, ho, wo, o], the
// kernel [(G,) k, k, c, o] of the strided convolution and a bias [(G,) c] give dx [(G,) n, h, w, c].
ffi::Error TransposedSelu(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> dy, ffi::Buffer<ffi::F32> kernel,
                          ffi::Buffer<ffi::F32> bias, ffi::ResultBuffer<ffi::F32> dx, int64_t stride, int64_t pad) {
  return RunConfigs(pool, kTransposedSelu, dx->dimensions(), dx->typed_data(), kernel.dimensions(),
                    kernel.typed_data(), dy.dimensions(), dy.typed_data(), stride, pad, &bias);
}

// The kernel gradient: x [(G,) n, h, w, c] and dy [(G,) n, ho, wo, o] give dk [(G,) k, k, c, o].
ffi::Error KernelGrad(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> x, ffi::Buffer<ffi::F32> dy,
                      ffi::ResultBuffer<ffi::F32> dk, int64_t stride, int64_t pad) {
  return RunConfigs(pool, kKernelGrad, x.dimensions(), x.typed_data(), dk->dimensions(), dk->typed_data(),
                    dy.dimensions(), dy.typed_data(), stride, pad);
}

// SELU(z + bias) for z [n, h, w, o] and bias [o]: one oneDNN binary addition with SELU's two
// eltwise post-ops (the transposed convolution's forward, oneDNN's input-gradient primitive,
// takes no post-ops of its own).
struct CachedSelu {
  int threads = 1;
  dnnl::binary add;
};

ffi::Error BiasSelu(ffi::Buffer<ffi::F32> z, ffi::Buffer<ffi::F32> bias, ffi::ResultBuffer<ffi::F32> y) {
  auto zd = z.dimensions(), bd = bias.dimensions();
  size_t rank = zd.size();
  if (rank != 4 && rank != 5) return ffi::Error::InvalidArgument("bias_selu: z [(G,) n, h, w, o] expected");
  int64_t g = rank == 5 ? zd[0] : 1, o = zd[rank - 1];
  if (bd.size() != rank - 3 || bd.back() != o || (rank == 5 && bd[0] != g))
    return ffi::Error::InvalidArgument("bias_selu: a bias per channel (and configuration) expected");
  int64_t m = zd[rank - 4] * zd[rank - 3] * zd[rank - 2];
  ThreadsFor threads;
  try {
    thread_local std::map<std::vector<int64_t>, CachedSelu> cache;
    std::vector<int64_t> key{g, m, o};
    // [G, n*h*w, o] plus a bias [G, 1, o] broadcast over the frames and pixels.
    memory::desc zm({g, m, o}, memory::data_type::f32, memory::format_tag::abc);
    memory::desc bm({g, 1, o}, memory::data_type::f32, memory::format_tag::abc);
    auto it = cache.find(key);
    if (it == cache.end()) {
      CachedSelu c;
      // An elementwise pass of G*n*h*w*o values: worth a team from a tenth of a convolution's work.
      c.threads = Parallel(double(g) * m * o * 10) ? g_threads : 1;
      omp_set_num_threads(c.threads);
      dnnl::primitive_attr attr = SeluAttr();
      c.add = dnnl::binary(dnnl::binary::primitive_desc(Engine(), dnnl::algorithm::binary_add, zm, bm, zm, attr));
      it = cache.emplace(key, std::move(c)).first;
    }
    threads.Use(it->second.threads);
    auto& stream = Stream();
    memory zmem(zm, Engine(), z.typed_data()), bmem(bm, Engine(), bias.typed_data()), ymem(zm, Engine(), y->typed_data());
    it->second.add.execute(stream, {{DNNL_ARG_SRC_0, zmem}, {DNNL_ARG_SRC_1, bmem}, {DNNL_ARG_DST, ymem}});
    stream.wait();
  } catch (const dnnl::error& e) {
    return ffi::Error::Internal(std::string("oneDNN bias and SELU failed: ") + e.what());
  }
  return ffi::Error::Success();
}

}  // namespace

#define CDRL_CONV_BINDING()                                                                        \
  ffi::Ffi::Bind().Ctx<ffi::ThreadPool>().Arg<ffi::Buffer<ffi::F32>>().Arg<ffi::Buffer<ffi::F32>>()  \
      .Ret<ffi::Buffer<ffi::F32>>().Attr<int64_t>("stride").Attr<int64_t>("padding")

// A pass with a bias too: frames, kernel, bias -> result.
#define CDRL_CONV_BIAS_BINDING()                                                                   \
  ffi::Ffi::Bind().Ctx<ffi::ThreadPool>().Arg<ffi::Buffer<ffi::F32>>().Arg<ffi::Buffer<ffi::F32>>()  \
      .Arg<ffi::Buffer<ffi::F32>>().Ret<ffi::Buffer<ffi::F32>>().Attr<int64_t>("stride").Attr<int64_t>("padding")

XLA_FFI_DEFINE_HANDLER_SYMBOL(CdrlConvForward, Forward, CDRL_CONV_BINDING());
XLA_FFI_DEFINE_HANDLER_SYMBOL(CdrlConvInputGrad, InputGrad, CDRL_CONV_BINDING());
XLA_FFI_DEFINE_HANDLER_SYMBOL(CdrlBiasSelu, BiasSelu,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>());
XLA_FFI_DEFINE_HANDLER_SYMBOL(CdrlConvForwardSelu, ForwardSelu, CDRL_CONV_BIAS_BINDING());
XLA_FFI_DEFINE_HANDLER_SYMBOL(CdrlConvKernelGrad, KernelGrad, CDRL_CONV_BINDING());
XLA_FFI_DEFINE_HANDLER_SYMBOL(CdrlConvTransposedSelu, TransposedSelu, CDRL_CONV_BIAS_BINDING());

// The OpenMP threads of a large pass (XLA's intra-op thread count), and the multiply-adds from
// which a pass is large; for the primitives made from now on.
extern "C" void CdrlOnednnSetThreads(int n, double parallel_macs) {
  g_threads = n;
  g_parallel_macs = parallel_macs;
}
