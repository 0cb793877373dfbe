// A CPU allocator for a control loop: every block libtorch frees is kept for the next request of its size, so after
// the first calls a package call's intermediate tensors reuse the blocks of earlier calls (no malloc, free or fresh
// page per call; BENCHMARKS.md, "Deploy: exported adapter tail latency", has what that saves). Blocks are never
// returned to the system: the pool holds the most blocks of each size that were live at once (a package's
// intermediates, a few MB). Install it once, before loading anything (use_reusing_cpu_allocator()); tensors made
// before keep their own deleter. Thread-safe (one mutex; a control loop's calls do not contend for it).
#pragma once

#include <c10/core/Allocator.h>
#include <c10/core/CPUAllocator.h>

#include <cstdlib>
#include <mutex>
#include <new>
#include <unordered_map>
#include <vector>

namespace bodyschema {

class ReusingCpuAllocator final : public c10::Allocator {
 public:
  c10::DataPtr allocate(size_t nbytes) override {
    void* data = nbytes == 0 ? nullptr : take(round_up(nbytes));
    return {data, data, &ReusingCpuAllocator::give_back, c10::Device(c10::DeviceType::CPU)};
  }
  c10::DeleterFnPtr raw_deleter() const override { return &ReusingCpuAllocator::give_back; }
  void copy_data(void* dest, const void* src, std::size_t count) const override {
    default_copy_data(dest, src, count);
  }

  static ReusingCpuAllocator& instance() {
    static ReusingCpuAllocator* allocator = new ReusingCpuAllocator();  // never destroyed: tensors may outlive main
    return *allocator;
  }

 private:
  static constexpr size_t kAlign = 64;  // libtorch's CPU alignment; the block's size is kept in the 64 bytes before it

  static size_t round_up(size_t nbytes) { return (nbytes + kAlign - 1) / kAlign * kAlign; }

  void* take(size_t size) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      auto& blocks = free_[size];
      if (!blocks.empty()) {
        void* data = blocks.back();
        blocks.pop_back();
        return data;
      }
    }
    char* base = static_cast<char*>(std::aligned_alloc(kAlign, size + kAlign));
    if (base == nullptr) throw std::bad_alloc();
    *reinterpret_cast<size_t*>(base) = size;
    return base + kAlign;
  }

  static void give_back(void* data) {
    if (data == nullptr) return;
    size_t size = *reinterpret_cast<size_t*>(static_cast<char*>(data) - kAlign);
    auto& self = instance();
    std::lock_guard<std::mutex> lock(self.mutex_);
    self.free_[size].push_back(data);
  }

  std::mutex mutex_;
  std::unordered_map<size_t, std::vector<void*>> free_;  // block size [bytes] -> blocks free to reuse
};

// libtorch's CPU allocator from now on: the reusing one (above the default's priority 0).
inline void use_reusing_cpu_allocator() { c10::SetCPUAllocator(&ReusingCpuAllocator::instance(), 1); }

}  // namespace bodyschema
