#include "clients/robot/learning/torch_archive.h"

#include <cstdio>
#include <filesystem>

namespace fleetmem::robot::learning {

std::string TorchMessage(const std::exception& e) {
  if (const auto* torch_error = dynamic_cast<const c10::Error*>(&e)) {
    return torch_error->what_without_backtrace();
  }
  return e.what();
}

void WriteModules(torch::serialize::OutputArchive& archive,
                  const NamedModules& modules) {
  for (const auto& [name, module] : modules) {
    torch::serialize::OutputArchive nested;
    module->save(nested);
    archive.write(name, nested);
  }
}

void ReadModules(torch::serialize::InputArchive& archive,
                 const NamedModules& modules) {
  for (const auto& [name, module] : modules) {
    torch::serialize::InputArchive nested;
    archive.read(name, nested);
    module->load(nested);
  }
}

absl::Status SaveModelArchive(
    const std::string& path, std::string_view magic, int64_t format,
    const std::function<void(torch::serialize::OutputArchive&)>& fill,
    const NamedModules& modules) {
  const std::string tmp = path + ".tmp";
  absl::StatusOr<bool> saved = Guarded<bool>("model", "save", [&] {
    torch::serialize::OutputArchive archive;
    archive.write("magic", c10::IValue(std::string(magic)));
    archive.write("format", c10::IValue(format));
    fill(archive);
    WriteModules(archive, modules);
    archive.save_to(tmp);
    return true;
  });
  if (!saved.ok()) {
    std::remove(tmp.c_str());
    return absl::InternalError(absl::StrCat("cannot write the model to ", path,
                                            ": ", saved.status().message()));
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    std::remove(tmp.c_str());
    return absl::InternalError(
        absl::StrCat("cannot rename ", tmp, " to ", path, ": ", ec.message()));
  }
  return absl::OkStatus();
}

absl::Status OpenModelArchive(const std::string& path, std::string_view magic,
                              int64_t format, std::string_view kind,
                              torch::serialize::InputArchive& archive) {
  if (!std::filesystem::exists(path)) {
    return absl::NotFoundError(absl::StrCat("no model file ", path));
  }
  try {
    archive.load_from(path);
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, " is not a readable ",
                                            std::string(kind),
                                            " file: ", TorchMessage(e)));
  }
  c10::IValue stored_magic, stored_format;
  if (!archive.try_read("magic", stored_magic) || !stored_magic.isString() ||
      stored_magic.toStringRef() != magic) {
    return absl::DataLossError(
        absl::StrCat(path, " is not a ", std::string(kind), " file"));
  }
  if (!archive.try_read("format", stored_format) || !stored_format.isInt() ||
      stored_format.toInt() != format) {
    return absl::FailedPreconditionError(absl::StrCat(
        path, " was written in ", std::string(kind), " format ",
        stored_format.isInt() ? std::to_string(stored_format.toInt()) : "?",
        "; this build reads format ", format));
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::robot::learning
