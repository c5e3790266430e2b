#include "services/common/files.h"

#include <stdlib.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <system_error>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace fleetmem::files {

absl::StatusOr<std::string> ReadFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot open ", path));
  std::stringstream bytes;
  bytes << in.rdbuf();
  if (in.bad()) return absl::DataLossError(absl::StrCat("cannot read ", path));
  return bytes.str();
}

absl::Status WriteFile(const std::string& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << text;
  out.close();
  if (!out) return absl::InternalError(absl::StrCat("cannot write ", path));
  return absl::OkStatus();
}

absl::StatusOr<std::string> MakeTempDir(const std::string& prefix) {
  const char* tmp = std::getenv("TMPDIR");
  std::string pattern = absl::StrCat(
      (tmp != nullptr && *tmp != '\0') ? tmp : "/tmp", "/", prefix, "XXXXXX");
  std::vector<char> buffer(pattern.begin(), pattern.end());
  buffer.push_back('\0');
  if (mkdtemp(buffer.data()) == nullptr) {
    return absl::InternalError(
        absl::StrCat("mkdtemp(", pattern, "): ", std::strerror(errno)));
  }
  return std::string(buffer.data());
}

absl::Status RemoveTree(const std::string& path) {
  std::error_code error;
  std::filesystem::remove_all(path, error);
  if (error) {
    return absl::InternalError(
        absl::StrCat("remove_all(", path, "): ", error.message()));
  }
  return absl::OkStatus();
}

TempDir::TempDir(const std::string& prefix) {
  absl::StatusOr<std::string> path = MakeTempDir(prefix);
  if (!path.ok()) {
    status_ = path.status();
    return;
  }
  path_ = *std::move(path);
}

TempDir::~TempDir() {
  if (path_.empty() || std::getenv("FLEETMEM_KEEP_TEST_DIRS") != nullptr) {
    return;
  }
  RemoveTree(path_).IgnoreError();
}

std::string TempDir::Join(const std::string& name) const {
  return absl::StrCat(path_, "/", name);
}

}  // namespace fleetmem::files
