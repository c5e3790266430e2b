// What the libtorch files of this module share: libtorch exceptions turned
// into statuses, and model files (a magic string, a format number, options
// and every module's weights as nested archives, written through a
// temporary file renamed into place). Included only by the module's .cc
// files that already include torch/torch.h.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_TORCH_ARCHIVE_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_TORCH_ARCHIVE_H_

#include <torch/nn/module.h>
#include <torch/serialize/archive.h>

#include <cstdint>
#include <functional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace fleetmem::robot::learning {

using NamedModules = std::vector<std::pair<std::string, torch::nn::Module*>>;

// An exception's message; libtorch's without the C++ backtrace it appends.
std::string TorchMessage(const std::exception& e);

// Runs `body`, turning any libtorch (c10::Error) or standard exception into
// INTERNAL "<component>: <what>: <message>".
template <typename T, typename Body>
absl::StatusOr<T> Guarded(std::string_view component, const char* what,
                          Body&& body) {
  try {
    return body();
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat(std::string(component), ": ", what,
                                            ": ", TorchMessage(e)));
  }
}

void WriteModules(torch::serialize::OutputArchive& archive,
                  const NamedModules& modules);
// Throws (c10::Error) when a module is missing or does not fit.
void ReadModules(torch::serialize::InputArchive& archive,
                 const NamedModules& modules);

// Writes `magic`, `format`, what `fill` adds and the modules to `path`.
// INTERNAL on an I/O error; the old file is then left as it was.
absl::Status SaveModelArchive(
    const std::string& path, std::string_view magic, int64_t format,
    const std::function<void(torch::serialize::OutputArchive&)>& fill,
    const NamedModules& modules);

// Loads `path` into `archive` and checks its magic and format: NOT_FOUND,
// DATA_LOSS (unreadable, or not a `kind` file) or FAILED_PRECONDITION
// (another format).
absl::Status OpenModelArchive(const std::string& path, std::string_view magic,
                              int64_t format, std::string_view kind,
                              torch::serialize::InputArchive& archive);

}  // namespace fleetmem::robot::learning

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_TORCH_ARCHIVE_H_
