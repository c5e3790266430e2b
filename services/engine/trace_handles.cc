#include "services/engine/trace_handles.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "services/core/validation.h"

namespace fleetmem::engine {

uint64_t TraceHandles::Find(const core::TraceKey& key) const {
  const std::optional<Packed> packed = robots_.Find(key.robot_id, key.seq);
  if (!packed.has_value()) return 0;
  auto it = handle_of_.find(*packed);
  return it == handle_of_.end() ? 0 : it->second;
}

std::optional<core::TraceKey> TraceHandles::Key(uint64_t handle) const {
  auto it = key_of_.find(handle);
  if (it == key_of_.end()) return std::nullopt;
  return robots_.Unpack(it->second);
}

void TraceHandles::Assign(const core::TraceKey& key, uint64_t handle) {
  const Packed packed = robots_.Pack(key.robot_id, key.seq);
  auto old_handle = handle_of_.find(packed);
  if (old_handle != handle_of_.end()) key_of_.erase(old_handle->second);
  auto old_key = key_of_.find(handle);
  if (old_key != key_of_.end()) handle_of_.erase(old_key->second);
  handle_of_[packed] = handle;
  key_of_[handle] = packed;
}

uint64_t TraceHandles::Erase(const core::TraceKey& key) {
  const std::optional<Packed> packed = robots_.Find(key.robot_id, key.seq);
  if (!packed.has_value()) return 0;
  auto it = handle_of_.find(*packed);
  if (it == handle_of_.end()) return 0;
  const uint64_t handle = it->second;
  key_of_.erase(handle);
  handle_of_.erase(it);
  return handle;
}

bool TraceHandles::EraseHandle(uint64_t handle) {
  auto it = key_of_.find(handle);
  if (it == key_of_.end()) return false;
  handle_of_.erase(it->second);
  key_of_.erase(it);
  return true;
}

void TraceHandles::Reserve(size_t count) {
  handle_of_.reserve(count);
  key_of_.reserve(count);
}

void TraceHandles::Clear() {
  robots_.Clear();
  handle_of_.clear();
  key_of_.clear();
}

void TraceHandles::ForEach(const std::function<void(uint64_t, std::string_view,
                                                    uint64_t)>& visit) const {
  for (const auto& [handle, key] : key_of_) {
    visit(handle, robots_.robot_id(key.robot), key.seq);
  }
}

uint64_t TraceHandles::SavedSize() const {
  uint64_t size = 8 + 8 + key_of_.size() * (4 + 8 + 8);
  for (uint32_t robot = 0; robot < robots_.size(); ++robot) {
    size += 8 + robots_.robot_id(robot).size();
  }
  return size;
}

void TraceHandles::Save(core::ByteWriter& out) const {
  out.Put<uint64_t>(robots_.size());
  for (uint32_t robot = 0; robot < robots_.size(); ++robot) {
    out.PutString(robots_.robot_id(robot));
  }
  out.Put<uint64_t>(key_of_.size());
  for (const auto& [handle, key] : key_of_) {
    out.Put<uint32_t>(key.robot);
    out.Put<uint64_t>(key.seq);
    out.Put<uint64_t>(handle);
  }
}

absl::Status TraceHandles::Load(core::ByteReader& in, uint64_t next_handle) {
  if (!empty() || robots_.size() != 0) {
    return absl::FailedPreconditionError(
        "trace handles: Load into a used table");
  }
  auto fail = [this](absl::Status status) {
    Clear();
    return status;
  };
  uint64_t robot_count = 0, count = 0;
  if (!in.Get(&robot_count) || robot_count > in.remaining()) {
    return fail(absl::DataLossError("bad robot count"));
  }
  for (uint64_t i = 0; i < robot_count; ++i) {
    std::string robot_id;
    if (!in.GetString(&robot_id, core::kMaxIdLength)) {
      return fail(absl::DataLossError("bad robot id"));
    }
    if (!robots_.Add(robot_id)) {
      return fail(absl::DataLossError(
          absl::StrCat("robot id \"", robot_id, "\" twice")));
    }
  }
  // An entry takes 20 bytes.
  if (!in.Get(&count) || count > in.remaining() / 20) {
    return fail(absl::DataLossError("bad trace count"));
  }
  Reserve(count);
  for (uint64_t i = 0; i < count; ++i) {
    Packed key;
    uint64_t handle = 0;
    if (!in.Get(&key.robot) || !in.Get(&key.seq) || !in.Get(&handle) ||
        key.robot >= robot_count || handle == 0 || handle >= next_handle) {
      return fail(absl::DataLossError(absl::StrCat("bad handle entry ", i)));
    }
    if (!handle_of_.try_emplace(key, handle).second ||
        !key_of_.try_emplace(handle, key).second) {
      return fail(
          absl::DataLossError(absl::StrCat("repeated handle entry ", i)));
    }
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::engine
