// Filter one state with an exported safety filter (`reach export ... --out f.onnx`), from C++ with
// ONNX Runtime's C++ API alone: no Python, no torch.
//
//   filter_one_state FILTER.onnx --state X1,X2,... --u U1,... [--t TIME_TO_GO]
//
// It makes the checks that reach_runtime/filter.py makes before and after running the graph, since
// a caller of the bare graph owns them (docs/export.md, "Fail closed"):
//   - the file is a reach filter of format reach-filter/1, with the graph's inputs and outputs;
//   - the state and the nominal input have the declared sizes and are finite after the cast to
//     float32 (a double of 1e300 overflows it);
//   - the time-to-go is finite and lies inside reach.time_range (with the runtime's slack of 1e-6
//     relative), and is given where the export declares no default (reach kinds);
//   - the batch is refused when the graph sets `untrusted` (a non-finite value, gradient or input).
// A refusal prints "refused: REASON" and exits 3; a usage or loading error exits 2; a decision
// prints the lines below and exits 0.
//
// Build: see build_and_run.sh (g++ -std=c++17 -I<ORT headers> ... -lonnxruntime).

#include <onnxruntime_cxx_api.h>

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

namespace {

const char* const kFormat = "reach-filter/1";
const double kTimeTolerance = 1e-6;  // reach_runtime.filter._TIME_TOLERANCE
const char* const kInputs[] = {"state", "time_to_go", "u_nominal"};
const char* const kOutputs[] = {"control", "value", "gradient", "intervened", "infeasible", "outside_domain", "untrusted"};
enum Output { kControl, kValue, kGradient, kIntervened, kInfeasible, kOutsideDomain, kUntrusted };

// Thrown for what the filter refuses to decide on (exit 3); std::runtime_error for the rest (exit 2).
struct Refusal : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// ---------------------------------------------------------------- the few JSON values read here
// The reach.* metadata values are JSON. This example reads only strings, numbers, null and a list
// of two numbers, and refuses anything else rather than guess.
std::string Trim(const std::string& text) {
  size_t a = text.find_first_not_of(" \t\r\n");
  size_t b = text.find_last_not_of(" \t\r\n");
  return a == std::string::npos ? "" : text.substr(a, b - a + 1);
}

double JsonNumber(const std::string& text, const std::string& key) {
  std::string t = Trim(text);
  const char* begin = t.c_str();
  char* end = nullptr;
  errno = 0;
  double value = std::strtod(begin, &end);
  if (t.empty() || end != begin + t.size() || errno == ERANGE || !std::isfinite(value) ||
      !(std::isdigit(static_cast<unsigned char>(t[0])) || t[0] == '-'))
    throw std::runtime_error("metadata reach." + key + " is not a finite number: " + text);
  return value;
}

bool JsonIsNull(const std::string& text) { return Trim(text) == "null"; }

std::string JsonString(const std::string& text, const std::string& key) {
  std::string t = Trim(text);
  if (t.size() < 2 || t.front() != '"' || t.back() != '"' || t.find('\\') != std::string::npos ||
      t.find('"', 1) != t.size() - 1)
    throw std::runtime_error("metadata reach." + key + " is not a plain JSON string: " + text);
  return t.substr(1, t.size() - 2);
}

std::vector<double> JsonNumberList(const std::string& text, const std::string& key) {
  std::string t = Trim(text);
  if (t.size() < 2 || t.front() != '[' || t.back() != ']')
    throw std::runtime_error("metadata reach." + key + " is not a JSON list: " + text);
  std::vector<double> values;
  std::string body = t.substr(1, t.size() - 2);
  size_t start = 0;
  while (!Trim(body).empty()) {
    size_t comma = body.find(',', start);
    values.push_back(JsonNumber(body.substr(start, comma - start), key));
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return values;
}

// ---------------------------------------------------------------- command-line values
// "a,b,c" as doubles; a token that is no number at all is a usage error, while "nan" or "inf" parse
// (strtod reads them) so that the finiteness check below is the one that refuses them.
std::vector<double> ParseList(const std::string& text, const std::string& what) {
  std::vector<double> values;
  size_t start = 0;
  while (true) {
    size_t comma = text.find(',', start);
    std::string token = Trim(text.substr(start, comma - start));
    const char* begin = token.c_str();
    char* end = nullptr;
    double value = std::strtod(begin, &end);  // an overflow reads as +-inf (refused below)
    if (token.empty() || end != begin + token.size())
      throw std::runtime_error(what + ": '" + token + "' is not a number");
    values.push_back(value);
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return values;
}

std::string Join(const std::vector<double>& values) {
  std::string out;
  char buffer[64];
  for (size_t i = 0; i < values.size(); ++i) {
    std::snprintf(buffer, sizeof buffer, "%s%.9g", i ? "," : "", values[i]);
    out += buffer;
  }
  return out;
}

// The values as float32, refusing a wrong size and NaN or inf after the cast (as reach_runtime does).
std::vector<float> Float32(const std::vector<double>& values, size_t dim, const std::string& what) {
  if (values.size() != dim)
    throw Refusal(what + " must have " + std::to_string(dim) + " entries, got " + std::to_string(values.size()));
  std::vector<float> cast(values.size());
  for (size_t i = 0; i < values.size(); ++i) {
    cast[i] = static_cast<float>(values[i]);
    if (!std::isfinite(cast[i]))
      throw Refusal(what + " contain NaN or inf (or overflow float32), e.g. [" + Join(values) + "]");
  }
  return cast;
}

struct Metadata {
  std::string system_name, problem, kind, source;
  size_t state_dim = 0, control_dim = 0;
  double time_low = 0, time_high = 0;
  bool has_default_time = false;
  double default_time = 0;
};

Metadata ReadMetadata(const Ort::Session& session) {
  Ort::AllocatorWithDefaultOptions allocator;
  Ort::ModelMetadata model = session.GetModelMetadata();
  auto get = [&](const std::string& key) -> std::string {
    Ort::AllocatedStringPtr value = model.LookupCustomMetadataMapAllocated(("reach." + key).c_str(), allocator);
    if (!value) throw std::runtime_error("metadata lacks reach." + key + " (export the file with `reach export`)");
    return value.get();
  };
  Ort::AllocatedStringPtr format = model.LookupCustomMetadataMapAllocated("reach.format", allocator);
  if (!format || JsonString(format.get(), "format") != kFormat)
    throw std::runtime_error(std::string("not a reach filter of format ") + kFormat + " (export it with `reach export`)");
  Metadata meta;
  meta.system_name = JsonString(get("system_name"), "system_name");
  meta.problem = JsonString(get("problem"), "problem");
  meta.source = JsonString(get("source"), "source");
  double state_dim = JsonNumber(get("state_dim"), "state_dim");
  double control_dim = JsonNumber(get("control_dim"), "control_dim");
  if (state_dim < 1 || control_dim < 1 || state_dim != std::floor(state_dim) || control_dim != std::floor(control_dim))
    throw std::runtime_error("metadata reach.state_dim or reach.control_dim is not a positive integer");
  meta.state_dim = static_cast<size_t>(state_dim);
  meta.control_dim = static_cast<size_t>(control_dim);
  std::vector<double> range = JsonNumberList(get("time_range"), "time_range");
  if (range.size() != 2 || !(range[0] <= range[1]))
    throw std::runtime_error("metadata reach.time_range is not [low, high]");
  meta.time_low = range[0];
  meta.time_high = range[1];
  std::string default_time = get("default_time_to_go");
  meta.has_default_time = !JsonIsNull(default_time);
  if (meta.has_default_time) meta.default_time = JsonNumber(default_time, "default_time_to_go");
  // the kind is one field of the settings object: read it as `"kind": "NAME"` without a JSON parser
  std::string settings = get("settings");
  size_t at = settings.find("\"kind\": \"");
  meta.kind = at == std::string::npos ? "?" : settings.substr(at + 9, settings.find('"', at + 9) - at - 9);
  return meta;
}

void CheckGraph(const Ort::Session& session) {
  Ort::AllocatorWithDefaultOptions allocator;
  std::vector<std::string> inputs, outputs;
  for (size_t i = 0; i < session.GetInputCount(); ++i) inputs.push_back(session.GetInputNameAllocated(i, allocator).get());
  for (size_t i = 0; i < session.GetOutputCount(); ++i) outputs.push_back(session.GetOutputNameAllocated(i, allocator).get());
  if (inputs != std::vector<std::string>(std::begin(kInputs), std::end(kInputs)))
    throw std::runtime_error("the graph's inputs are not [state, time_to_go, u_nominal]");
  for (const char* name : kOutputs) {
    bool found = false;
    for (const std::string& output : outputs) found = found || output == name;
    if (!found) throw std::runtime_error(std::string("the graph lacks the output ") + name);
  }
}

// The time-to-go to use: the given one, or the export's default; refused outside reach.time_range.
double TimeToGo(const Metadata& meta, const char* given) {
  double t;
  if (given == nullptr) {
    if (!meta.has_default_time)
      throw Refusal("this " + meta.problem + " filter of " + meta.system_name +
                    " needs the time-to-go --t (it counts down with the task's deadline)");
    t = meta.default_time;
  } else {
    std::vector<double> values = ParseList(given, "--t");
    if (values.size() != 1) throw std::runtime_error("--t takes one number");
    t = values[0];
  }
  double tol = kTimeTolerance * std::fmax(1.0, std::fabs(meta.time_high));
  if (!std::isfinite(t) || t < meta.time_low - tol || t > meta.time_high + tol) {
    char message[256];
    std::snprintf(message, sizeof message,
                  "time-to-go t = %.9g lies outside [%g, %g], the times this value function covers", t,
                  meta.time_low, meta.time_high);
    throw Refusal(message);
  }
  return t;
}

template <typename T>
std::vector<T> Read(const Ort::Value& value, size_t count, const char* name) {
  if (!value.IsTensor() || value.GetTensorTypeAndShapeInfo().GetElementCount() != count)
    throw std::runtime_error(std::string("the graph's output ") + name + " has an unexpected shape");
  const T* data = value.GetTensorData<T>();
  return std::vector<T>(data, data + count);
}

int Main(int argc, char** argv) {
  const char *path = nullptr, *state_arg = nullptr, *u_arg = nullptr, *t_arg = nullptr;
  for (int i = 1; i < argc; ++i) {
    std::string arg = argv[i];
    if ((arg == "--state" || arg == "--u" || arg == "--t") && i + 1 < argc) {
      (arg == "--state" ? state_arg : arg == "--u" ? u_arg : t_arg) = argv[++i];
    } else if (path == nullptr && arg.rfind("--", 0) != 0) {
      path = argv[i];
    } else {
      throw std::runtime_error("unexpected argument '" + arg + "'");
    }
  }
  if (path == nullptr || state_arg == nullptr || u_arg == nullptr)
    throw std::runtime_error("usage: filter_one_state FILTER.onnx --state X1,X2,... --u U1,... [--t TIME_TO_GO]");
  std::vector<double> state_in = ParseList(state_arg, "--state");
  std::vector<double> u_in = ParseList(u_arg, "--u");

  // One intra-op thread, sequential, warnings off: as reach_runtime's Filter.load(threads=1).
  Ort::Env env(ORT_LOGGING_LEVEL_ERROR, "reach");
  Ort::SessionOptions options;
  options.SetIntraOpNumThreads(1);
  options.SetInterOpNumThreads(1);
  options.SetExecutionMode(ExecutionMode::ORT_SEQUENTIAL);
  options.SetLogSeverityLevel(3);
  Ort::Session session(env, path, options);
  CheckGraph(session);
  Metadata meta = ReadMetadata(session);
  std::printf("filter: %s of %s (%s problem), state_dim %zu, control_dim %zu, time_to_go in [%g, %g], source %s\n",
              meta.kind.c_str(), meta.system_name.c_str(), meta.problem.c_str(), meta.state_dim, meta.control_dim,
              meta.time_low, meta.time_high, meta.source.c_str());

  // The checks before the graph runs.
  std::vector<float> state = Float32(state_in, meta.state_dim, "states");
  std::vector<float> u_nominal = Float32(u_in, meta.control_dim, "u_nominal");
  float time_to_go = static_cast<float>(TimeToGo(meta, t_arg));

  // One state: a batch of one.
  Ort::MemoryInfo memory = Ort::MemoryInfo::CreateCpu(OrtArenaAllocator, OrtMemTypeDefault);
  const int64_t state_shape[] = {1, static_cast<int64_t>(meta.state_dim)};
  const int64_t time_shape[] = {1};
  const int64_t u_shape[] = {1, static_cast<int64_t>(meta.control_dim)};
  std::vector<Ort::Value> inputs;
  inputs.push_back(Ort::Value::CreateTensor<float>(memory, state.data(), state.size(), state_shape, 2));
  inputs.push_back(Ort::Value::CreateTensor<float>(memory, &time_to_go, 1, time_shape, 1));
  inputs.push_back(Ort::Value::CreateTensor<float>(memory, u_nominal.data(), u_nominal.size(), u_shape, 2));
  std::vector<Ort::Value> out = session.Run(Ort::RunOptions{nullptr}, kInputs, inputs.data(), inputs.size(), kOutputs,
                                            sizeof kOutputs / sizeof kOutputs[0]);

  // The check after: never pass on a decision made on a value the graph does not trust.
  if (Read<bool>(out[kUntrusted], 1, "untrusted")[0])
    throw Refusal(
        "the value function returned a non-finite value, gradient or optimal input in this batch; "
        "the filter does not trust it and keeps no nominal input");

  std::vector<float> control = Read<float>(out[kControl], meta.control_dim, "control");
  float value = Read<float>(out[kValue], 1, "value")[0];
  std::vector<float> gradient = Read<float>(out[kGradient], meta.state_dim, "gradient");
  bool intervened = Read<bool>(out[kIntervened], 1, "intervened")[0];
  bool infeasible = Read<bool>(out[kInfeasible], 1, "infeasible")[0];
  bool outside = Read<bool>(out[kOutsideDomain], 1, "outside_domain")[0];

  std::printf("time_to_go: %.9g%s\n", time_to_go, t_arg ? "" : " (the export's default)");
  std::printf("decision: %s\n", intervened ? "intervened (the filter's input replaces the nominal one)"
                                           : "passed (the nominal input is applied)");
  std::printf("nominal: %s\n", Join(std::vector<double>(u_nominal.begin(), u_nominal.end())).c_str());
  std::printf("control: %s\n", Join(std::vector<double>(control.begin(), control.end())).c_str());
  std::printf("value: %.9g\n", value);
  std::printf("gradient: %s\n", Join(std::vector<double>(gradient.begin(), gradient.end())).c_str());
  std::printf("flags: intervened=%d infeasible=%d outside_domain=%d\n", intervened, infeasible, outside);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Main(argc, argv);
  } catch (const Refusal& refusal) {
    std::printf("refused: %s\n", refusal.what());
    return 3;
  } catch (const Ort::Exception& error) {
    std::fprintf(stderr, "error: ONNX Runtime: %s\n", error.what());
    return 2;
  } catch (const std::exception& error) {
    std::fprintf(stderr, "error: %s\n", error.what());
    return 2;
  }
}
