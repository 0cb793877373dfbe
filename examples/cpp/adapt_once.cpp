// One adapted command from an exported adapter package, printed as one JSON line.
//   adapt_once PACKAGE.pt2 --q 0.3,-0.2 [--cut m1,m2] [--jam m=l_fixed_m,...] [--weak m=f_max_n,...]
//              [--band m=lo_m:hi_m,...] [--seed N] [--sha256 HEX]
// Runs a diffusion or a structured package alike. --sha256: refuse a package whose digest is not HEX (the one the
// export printed) before loading it. Exit codes: 0 a result was printed (its "status" says whether to send it),
// 1 the package cannot be used (missing, corrupt, another digest), 2 bad arguments.
#include <cstdio>
#include <iostream>
#include <sstream>

#include "adapter.h"

namespace {

std::vector<std::string> split(const std::string& text, char sep) {
  std::vector<std::string> out;
  std::stringstream stream(text);
  std::string item;
  while (std::getline(stream, item, sep))
    if (!item.empty()) out.push_back(item);
  return out;
}

double number(const std::string& text, const std::string& where) {
  size_t used = 0;
  double value = 0.0;
  try {
    value = std::stod(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  if (used == 0 || used != text.size()) throw std::invalid_argument(where + ": '" + text + "' is not a number");
  return value;
}

// "name=value" pairs into column `index(name)` of row 0 of `target` (a value "lo:hi" fills two tensors).
void fill_pairs(bodyschema::Adapter& adapter, const std::string& arg, const std::string& flag, torch::Tensor target,
                torch::Tensor second = {}, torch::Tensor mask = {}) {
  for (const auto& pair : split(arg, ',')) {
    auto eq = pair.find('=');
    if (eq == std::string::npos) throw std::invalid_argument(flag + " '" + pair + "': expected muscle=value");
    int j = adapter.muscle_index(pair.substr(0, eq));
    std::string value = pair.substr(eq + 1);
    if (second.defined()) {
      auto parts = split(value, ':');
      if (parts.size() != 2) throw std::invalid_argument(flag + " '" + pair + "': expected muscle=lo:hi");
      target[0][j] = number(parts[0], flag);
      second[0][j] = number(parts[1], flag);
    } else {
      target[0][j] = number(value, flag);
    }
    if (mask.defined()) mask[0][j] = 1.0;
  }
}

std::string json_list(const torch::Tensor& row) {
  std::ostringstream out;
  out.precision(17);
  out << "[";
  for (int64_t i = 0; i < row.size(0); ++i) {
    double v = row[i].item<double>();
    out << (i ? ", " : "");
    if (std::isfinite(v)) out << v; else out << "NaN";
  }
  return out.str() + "]";
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::cerr << "usage: adapt_once PACKAGE.pt2 --q q1,q2,... [--cut m,...] [--jam m=l,...] [--weak m=f,...] "
                 "[--band m=lo:hi,...] [--seed N] [--sha256 HEX]\n";
    return 2;
  }
  std::string pinned;  // read first: the digest is checked before the package is loaded
  for (int i = 2; i + 1 < argc; i += 2)
    if (std::string(argv[i]) == "--sha256") pinned = argv[i + 1];
  auto adapter = bodyschema::open_adapter(argv[1], pinned);
  if (!adapter) return 1;
  auto inputs = adapter->make_inputs(1);
  try {
    bool have_q = false;
    for (int i = 2; i < argc; i += 2) {
      std::string flag = argv[i];
      if (i + 1 >= argc) throw std::invalid_argument(flag + " needs a value");
      std::string value = argv[i + 1];
      if (flag == "--q") {
        auto parts = split(value, ',');
        if (parts.size() != adapter->joints.size())
          throw std::invalid_argument("--q has " + std::to_string(parts.size()) + " values; the package's joints are " +
                                      std::to_string(adapter->joints.size()));
        for (size_t j = 0; j < parts.size(); ++j) inputs[0][0][j] = number(parts[j], "--q");
        have_q = true;
      } else if (flag == "--cut") {
        for (const auto& name : split(value, ',')) inputs[1][0][adapter->muscle_index(name)] = 1.0;
      } else if (flag == "--jam") {
        fill_pairs(*adapter, value, flag, inputs[3], {}, inputs[2]);
      } else if (flag == "--weak") {
        fill_pairs(*adapter, value, flag, inputs[4]);
      } else if (flag == "--band") {
        fill_pairs(*adapter, value, flag, inputs[5], inputs[6]);
      } else if (flag == "--sha256") {
        // checked before loading
      } else if (flag == "--seed") {
        inputs[7] = torch::scalar_tensor(static_cast<int64_t>(number(value, "--seed")), torch::kInt64);
      } else {
        throw std::invalid_argument("unknown option " + flag);
      }
    }
    if (!have_q) throw std::invalid_argument("--q is required");
  } catch (const bodyschema::NotThisRobot& e) {
    std::cerr << "error: " << e.what() << "\n";
    return 1;
  } catch (const std::exception& e) {
    std::cerr << "error: " << e.what() << "\n";
    return 2;
  }
  std::vector<torch::Tensor> out;
  try {
    out = adapter->run(inputs);
  } catch (const std::exception& e) {
    std::string what = e.what();
    std::cerr << "error: the package failed to run: " << what.substr(0, what.find('\n')) << "\n";
    return 1;
  }
  int code = out[2][0].item<int>();
  auto name = adapter->status_names.count(code) ? adapter->status_names.at(code) : std::to_string(code);
  std::cout << "{\"status\": \"" << name << "\", \"status_code\": " << code << ", \"l_motor_m\": "
            << json_list(out[0][0]) << ", \"f_n\": " << json_list(out[1][0]) << "}" << std::endl;
  return 0;
}
