// A control loop a user can copy: load the package once, allocate the input buffers once, one call per tick.
//   control_loop PACKAGE.pt2 [--ticks 10000] [--cut muscle] [--json] [--sha256 HEX] [--system-allocator]
// Each tick writes the next posture of a slow sweep inside the joint ranges (metadata) into the q buffer (a real
// controller writes its reference posture and current faults there), calls the package and uses the command only
// when the status is 0 (ok). Prints the call latency percentiles [us], the first call's latency and the resident memory
// growth [kB] over the loop and the package's program the loop calls ("batch1" where the package holds one, else
// "model"). Runs a diffusion or a structured package alike; --sha256 refuses a package whose digest
// is not HEX before loading it (exit 1). libtorch's CPU tensors come from bodyschema::ReusingCpuAllocator (a call's
// intermediates reuse earlier calls' blocks); --system-allocator keeps libtorch's default (malloc per tensor).
#include <algorithm>
#include <chrono>
#include <fstream>
#include <iostream>

#include "adapter.h"
#include "reusing_allocator.h"

namespace {

long rss_kb() {  // resident set size from /proc (Linux)
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::stol(line.substr(6));
  return -1;
}

double percentile(std::vector<double> v, double p) {
  std::sort(v.begin(), v.end());
  size_t i = std::min(v.size() - 1, static_cast<size_t>(p / 100.0 * (v.size() - 1) + 0.5));
  return v[i];
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::cerr << "usage: control_loop PACKAGE.pt2 [--ticks N] [--cut muscle] [--json] [--sha256 HEX] "
                 "[--system-allocator]\n";
    return 2;
  }
  long ticks = 10000;
  std::string cut, pinned;
  bool json = false, system_allocator = false;
  for (int i = 2; i < argc; ++i) {
    std::string flag = argv[i];
    if (flag == "--ticks" && i + 1 < argc) ticks = std::stol(argv[++i]);
    else if (flag == "--cut" && i + 1 < argc) cut = argv[++i];
    else if (flag == "--json") json = true;
    else if (flag == "--sha256" && i + 1 < argc) pinned = argv[++i];
    else if (flag == "--system-allocator") system_allocator = true;
    else { std::cerr << "error: unknown option " << flag << "\n"; return 2; }
  }
  if (ticks < 1) { std::cerr << "error: --ticks must be >= 1\n"; return 2; }
  at::set_num_threads(1);
  if (!system_allocator) bodyschema::use_reusing_cpu_allocator();  // before loading: the package's tensors too
  using clock = std::chrono::steady_clock;
  auto t_load = clock::now();
  auto adapter = bodyschema::open_adapter(argv[1], pinned);
  if (!adapter) return 1;
  double load_ms = std::chrono::duration<double, std::milli>(clock::now() - t_load).count();
  auto inputs = adapter->make_inputs(1);  // the buffers: allocated once, written every tick
  if (!cut.empty()) {
    try { inputs[1][0][adapter->muscle_index(cut)] = 1.0; }
    catch (const std::exception& e) { std::cerr << "error: " << e.what() << "\n"; return 1; }  // NotThisRobot
  }
  double* q = inputs[0].data_ptr<double>();
  const size_t n = adapter->joints.size();
  std::vector<double> lat_us(ticks, 0.0);  // written (so resident) before the memory baseline is taken
  long sent = 0, rss_start = 0;
  double first_us = 0.0;
  for (long t = 0; t <= ticks; ++t) {
    for (size_t j = 0; j < n; ++j) {  // the reference posture of this tick: a slow sweep inside the joint ranges
      const double lo = adapter->q_range[2 * j], hi = adapter->q_range[2 * j + 1];
      q[j] = lo + (hi - lo) * (0.5 + 0.4 * std::sin(0.001 * t + j));
    }
    auto start = clock::now();
    auto out = adapter->run(inputs);
    double us = std::chrono::duration<double, std::micro>(clock::now() - start).count();
    if (t == 0) { first_us = us; rss_start = rss_kb(); continue; }  // the first call after loading, reported alone
    if (out[2].data_ptr<int>()[0] == 0) ++sent;  // status ok: out[0], out[1] hold the command to send
    lat_us[t - 1] = us;
  }
  long rss_growth = rss_kb() - rss_start;
  if (json) {
    std::cout << "{\"ticks\": " << ticks << ", \"load_ms\": " << load_ms << ", \"first_call_us\": " << first_us
              << ", \"p50_us\": " << percentile(lat_us, 50) << ", \"p99_us\": " << percentile(lat_us, 99)
              << ", \"p999_us\": " << percentile(lat_us, 99.9) << ", \"max_us\": " << percentile(lat_us, 100)
              << ", \"rss_growth_kb\": " << rss_growth << ", \"ok_ticks\": " << sent << ", \"program\": \""
              << adapter->program_for(1) << "\"}" << std::endl;
  } else {
    std::cout << ticks << " ticks, " << sent << " ok; load " << load_ms << " ms, first call " << first_us
              << " us; p50 " << percentile(lat_us, 50) << " us, p99 " << percentile(lat_us, 99) << " us, p99.9 "
              << percentile(lat_us, 99.9) << " us, max " << percentile(lat_us, 100) << " us; RSS growth "
              << rss_growth << " kB; program " << adapter->program_for(1) << std::endl;
  }
  return 0;
}
