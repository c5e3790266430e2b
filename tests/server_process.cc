#include "tests/server_process.h"

#include "gtest/gtest.h"

namespace fleetmem::testing {

TempDir::TempDir(const std::string& prefix) : files::TempDir(prefix) {
  if (!status().ok()) {
    ADD_FAILURE() << "cannot make a temporary directory: " << status();
  }
}

std::string ReadFileOrEmpty(const std::string& path) {
  absl::StatusOr<std::string> text = files::ReadFile(path);
  return text.ok() ? *std::move(text) : std::string();
}

}  // namespace fleetmem::testing
