// Test utility: a small tmpfs to fill up (disk-full tests). Mounting needs
// root; tests skip with why_not() otherwise.
#ifndef FLEETMEM_TESTS_SMALL_FILESYSTEM_H_
#define FLEETMEM_TESTS_SMALL_FILESYSTEM_H_

#include <cstdint>
#include <string>

namespace fleetmem::testing {

inline constexpr uint64_t kMiB = 1 << 20;

// A tmpfs of `size_mib` mounted on the existing directory `path`; unmounted
// (lazily, so a leftover process cannot block it) by the destructor.
class SmallFilesystem {
 public:
  SmallFilesystem(const std::string& path, int size_mib);
  ~SmallFilesystem();
  SmallFilesystem(const SmallFilesystem&) = delete;
  SmallFilesystem& operator=(const SmallFilesystem&) = delete;

  bool mounted() const { return mounted_; }
  const std::string& why_not() const { return why_not_; }

 private:
  std::string path_;
  bool mounted_ = false;
  std::string why_not_;
};

// Free bytes under `path`.
uint64_t FreeBytes(const std::string& path);

// Writes a file of `bytes` zeros (leaving the filesystem that much fuller).
void Fill(const std::string& file, uint64_t bytes);

}  // namespace fleetmem::testing

#endif  // FLEETMEM_TESTS_SMALL_FILESYSTEM_H_
