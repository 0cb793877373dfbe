// The exported adapter package (lightning_bodyschema.deploy) from C++: load it, read its metadata, build its inputs.
// Inputs, in order (float64 unless said): q_ref (B, N) [rad]; cut, jam (B, M) masks 0/1; l_fixed_m (B, M) [m];
// f_weak_n (B, M) [N]; band_lo_m, band_hi_m (B, M) [m] (NaN where a fault does not apply); seed () int64.
// Outputs: l_motor_m (B, M) [m], f_n (B, M) [N] (NaN rows unless ok), status (B,) int32 (metadata "status_codes").
// The same for a diffusion and a structured package (metadata "schema_kind"). A dynamic-batch package holds two
// programs (metadata "programs": "dynamic,1"): "model" for any batch and "batch1" for exactly one case; Adapter::run
// calls "batch1" for one case. A static package, and one written before, holds "model" alone. A package holds
// compiled shared libraries and loading it runs their code: pin the SHA-256 the export printed (open_adapter's
// `sha256`).
#pragma once

#include <torch/csrc/inductor/aoti_package/model_package_loader.h>
#include <torch/torch.h>

#include <cctype>
#include <cmath>
#include <iostream>
#include <limits>
#include <map>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "sha256.h"

namespace bodyschema {

// A request the package cannot answer for this robot (a fault on a muscle it does not have): exit 1, like a package
// that does not load; plain std::invalid_argument is a malformed command line (exit 2).
struct NotThisRobot : std::invalid_argument {
  using std::invalid_argument::invalid_argument;
};

// A JSON array of strings, e.g. ["a", "b"] (what the package's metadata holds for names).
inline std::vector<std::string> parse_string_list(const std::string& json) {
  std::vector<std::string> out;
  size_t i = 0;
  while ((i = json.find('"', i)) != std::string::npos) {
    size_t j = json.find('"', i + 1);
    if (j == std::string::npos) throw std::runtime_error("bad string list in package metadata: " + json);
    out.push_back(json.substr(i + 1, j - i - 1));
    i = j + 1;
  }
  return out;
}

// A flat JSON object of integers, e.g. {"ok": 0, "non_finite": 1} -> code -> name.
inline std::map<int, std::string> parse_status_codes(const std::string& json) {
  std::map<int, std::string> out;
  size_t i = 0;
  while ((i = json.find('"', i)) != std::string::npos) {
    size_t j = json.find('"', i + 1);
    size_t colon = json.find(':', j);
    if (j == std::string::npos || colon == std::string::npos) throw std::runtime_error("bad status_codes: " + json);
    out[std::stoi(json.substr(colon + 1))] = json.substr(i + 1, j - i - 1);
    i = json.find_first_of(",}", colon);
  }
  return out;
}

// A JSON array of numbers at any depth, flattened, e.g. [[-1.5, 1.5], [0, 2.2]] (the metadata's joint ranges).
inline std::vector<double> parse_numbers(const std::string& json) {
  std::vector<double> out;
  size_t i = 0;
  while ((i = json.find_first_of("-0123456789", i)) != std::string::npos) {
    size_t used = 0;
    out.push_back(std::stod(json.substr(i), &used));
    i += used;
  }
  return out;
}

struct Adapter {
  std::unique_ptr<torch::inductor::AOTIModelPackageLoader> loader;  // "model": the package's first program
  std::unique_ptr<torch::inductor::AOTIModelPackageLoader> batch1;  // "batch1" where the package holds it
  std::vector<std::string> joints, muscles;
  std::vector<double> q_range;  // lo, hi of each joint [rad], in joint order
  std::map<int, std::string> status_names;
  std::string kind;  // "diffusion" or "structured"
  int64_t default_seed = 0;

  // Throws std::runtime_error (with the reason) for a missing, corrupt or foreign package.
  explicit Adapter(const std::string& path) {
    loader = load_program(path, "model");
    auto meta = loader->get_metadata();
    if (meta["format"] != "lightning_bodyschema.adapter/1")
      throw std::runtime_error(path + " is not a lightning_bodyschema adapter package");
    const std::string programs = meta.count("programs") ? "," + meta.at("programs") + "," : "";
    if (programs.find(",1,") != std::string::npos && programs.rfind(",1,", 0) != 0)  // a second program, for 1 case
      batch1 = load_program(path, "batch1");
    joints = parse_string_list(meta.at("joint_names"));
    muscles = parse_string_list(meta.at("muscle_names"));
    status_names = parse_status_codes(meta.at("status_codes"));
    kind = meta.count("schema_kind") ? meta.at("schema_kind") : "diffusion";
    q_range = parse_numbers(meta.at("q_range_rad"));
    if (q_range.size() != 2 * joints.size()) throw std::runtime_error(path + ": bad q_range_rad in its metadata");
    default_seed = std::stoll(meta.at("seeds").substr(1));
  }

  int muscle_index(const std::string& name) const {
    for (size_t i = 0; i < muscles.size(); ++i)
      if (muscles[i] == name) return static_cast<int>(i);
    std::string known;
    for (const auto& m : muscles) known += (known.empty() ? "" : ", ") + m;
    throw NotThisRobot("unknown muscle '" + name + "'; the package's muscles are: " + known);
  }

  // Inputs for `batch` healthy cases (q zero, no fault): allocate once, then write into them every tick.
  std::vector<torch::Tensor> make_inputs(int64_t batch) const {
    auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
    const int64_t n = static_cast<int64_t>(joints.size()), m = static_cast<int64_t>(muscles.size());
    const double nan = std::numeric_limits<double>::quiet_NaN();
    return {torch::zeros({batch, n}, f64), torch::zeros({batch, m}, f64), torch::zeros({batch, m}, f64),
            torch::full({batch, m}, nan, f64), torch::full({batch, m}, nan, f64), torch::full({batch, m}, nan, f64),
            torch::full({batch, m}, nan, f64), torch::scalar_tensor(default_seed, torch::kInt64)};
  }

  // The program a call with `batch` cases runs: "batch1" for one case where the package holds it, else "model".
  std::string program_for(int64_t batch) const { return batch == 1 && batch1 ? "batch1" : "model"; }

  // One call: {l_motor_m (B, M), f_n (B, M), status (B,)}, by the program_for its number of cases.
  std::vector<torch::Tensor> run(const std::vector<torch::Tensor>& inputs) {
    return (inputs[0].size(0) == 1 && batch1 ? batch1 : loader)->run(inputs);
  }

 private:
  static std::unique_ptr<torch::inductor::AOTIModelPackageLoader> load_program(const std::string& path,
                                                                               const std::string& name) {
    try {
      return std::make_unique<torch::inductor::AOTIModelPackageLoader>(path, name);
    } catch (const std::exception& e) {
      std::string what = e.what();
      throw std::runtime_error("cannot load adapter package " + path + ": " + what.substr(0, what.find('\n')));
    }
  }
};

// The package at `path`, or nullptr after printing "error: <reason>" on stderr (a program then exits 1). With a
// pinned `sha256` (64 hex digits) a file with another digest is refused before anything in it is loaded.
inline std::unique_ptr<Adapter> open_adapter(const std::string& path, std::string sha256 = "") {
  try {
    if (!sha256.empty()) {
      for (auto& c : sha256) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
      if (sha256.size() != 64 || sha256.find_first_not_of("0123456789abcdef") != std::string::npos)
        throw std::runtime_error("--sha256 '" + sha256 + "': give the 64 hex digits the export printed");
      std::string actual = file_sha256(path);
      if (actual != sha256)
        throw std::runtime_error(path + " has SHA-256 " + actual + ", not the pinned " + sha256 +
                                 ": refused unloaded (a package runs compiled code)");
    }
    return std::make_unique<Adapter>(path);
  } catch (const std::exception& e) {
    std::cerr << "error: " << e.what() << "\n";
    return nullptr;
  }
}

}  // namespace bodyschema
