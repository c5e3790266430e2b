// Values of the RocksDB store: domain types <-> records.proto bytes.
// Internal to services/storage; the protobuf types stay in record_codec.cc.
//
// Every Decode* returns DATA_LOSS naming `key` (keys::Describe) when the bytes
// do not parse or do not match the key they were read from.
#ifndef FLEETMEM_SERVICES_STORAGE_RECORD_CODEC_H_
#define FLEETMEM_SERVICES_STORAGE_RECORD_CODEC_H_

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/functional/function_ref.h"
#include "absl/status/statusor.h"
#include "services/core/types.h"
#include "services/engine/fleet_log.h"
#include "services/engine/memory_store.h"

namespace fleetmem::storage {

// A cluster as stored: its traces are separate records, listed by key in the
// cluster's order.
struct StoredCluster {
  uint64_t id = 0;
  std::string robot_id;
  std::vector<float> centroid;
  std::vector<core::TraceKey> members;
};

std::string EncodeMeta(const engine::FleetMeta& meta);
absl::StatusOr<engine::FleetMeta> DecodeMeta(std::string_view key,
                                             std::string_view value);

// Pending and static-memory traces alike (cluster_id is 0 while pending),
// with the code inside: pending records and fleet images.
std::string EncodeTrace(const core::MemoryTrace& trace);
absl::StatusOr<core::MemoryTrace> DecodeTrace(std::string_view key,
                                              std::string_view value);
// A static-memory trace's record without its code, which goes under
// keys::CodeKey (EncodeCode). DecodeTrace reads it back with an empty code
// (and a record of layout 1 with its code).
std::string EncodeTraceWithoutCode(const core::MemoryTrace& trace);

// A code under keys::CodeKey: its floats, 4 bytes each, little-endian (the
// bytes are the floats in memory: no parse). DecodeCode fills `code`;
// DATA_LOSS naming `key` for an empty value or one not a whole number of
// floats.
std::string EncodeCode(std::span<const float> code);
absl::Status DecodeCode(std::string_view key, std::string_view value,
                        std::vector<float>* code);

std::string EncodeCluster(const StoredCluster& cluster);
absl::StatusOr<StoredCluster> DecodeCluster(std::string_view key,
                                            std::string_view value);

std::string EncodeRobot(const engine::RobotRecord& robot);
absl::StatusOr<engine::RobotRecord> DecodeRobot(std::string_view key,
                                                std::string_view value);

std::string EncodeEvent(const core::MemoryEvent& event);
absl::StatusOr<core::MemoryEvent> DecodeEvent(std::string_view key,
                                              std::string_view value);

// A local log's entry (segment_log.h): its record. Decoding checks every
// trace as DecodeTrace would.
std::string EncodeLoggedRecord(const engine::LogRecord& record);
// The same bytes, sized before they are written, so that they can go
// straight into a caller's buffer (the log's appends; its messages live on
// an arena: one allocation, not one per trace and field).
class LoggedRecordBytes {
 public:
  explicit LoggedRecordBytes(const engine::LogRecord& record);
  ~LoggedRecordBytes();
  LoggedRecordBytes(LoggedRecordBytes&&) noexcept;
  LoggedRecordBytes& operator=(LoggedRecordBytes&&) noexcept;
  size_t size() const;
  // Writes exactly size() bytes at `out`.
  void WriteTo(char* out) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};
// An upload an earlier build kept in RocksDB under keys::LogKey, as an
// entry (its sequence from the key).
absl::StatusOr<engine::LogEntry> DecodeLoggedUpload(std::string_view key,
                                                    std::string_view value);
// The record of a local log entry's bytes; DATA_LOSS naming `where` when
// they do not parse or hold no record (or two).
absl::StatusOr<engine::StoredRecord> DecodeLoggedRecord(std::string_view where,
                                                        std::string_view value);

// The traces of a fleet's clusters as they are read, before the cluster
// records that list them: added in any order (a scan's are in key order),
// then each taken once by AssembleCluster. A sorted vector, not a map: a
// load of 1,000,000 traces allocated a map node for each. A search starts
// where the last one ended and gallops outward: a cluster's members, and
// the next cluster's, are mostly one robot's segment, close together in
// key order (at 10,000,000 traces a binary search over the whole table per
// member took 19.7 s of a restart, a cache miss per step).
class TraceTable {
 public:
  // A key added twice is taken once: the other copy is left over (a load
  // reports it as a trace of no cluster).
  void Add(core::MemoryTrace trace);
  // The trace under `key`, moved out, if it is here, not taken and of
  // cluster `cluster_id`; else nullopt.
  std::optional<core::MemoryTrace> Take(const core::TraceKey& key,
                                        uint64_t cluster_id);
  // Traces added.
  size_t size() const { return traces_.size(); }
  // A trace no cluster took, or nullptr when every one was.
  const core::MemoryTrace* AnyLeft() const;
  // Calls `visit` with each trace not taken, ascending by key (the order of
  // a scan of their keys), until it fails; returns its status.
  absl::Status ForEach(
      absl::FunctionRef<absl::Status(core::MemoryTrace&)> visit);

 private:
  void Sort();
  // Index of the first trace not less than `key` (sorted), searched from
  // hint_ outward in O(log distance); leaves hint_ there.
  size_t LowerBound(const core::TraceKey& key);

  std::vector<core::MemoryTrace> traces_;
  std::vector<bool> taken_;
  size_t left_ = 0;
  size_t hint_ = 0;
  bool sorted_ = true;
};

// Moves the member traces of `stored` (read at `key`) out of `traces` into
// a new cluster at the end of `clusters`; DATA_LOSS if a member has no
// trace of this cluster there.
absl::Status AssembleCluster(std::string_view key, StoredCluster stored,
                             TraceTable* traces,
                             std::vector<core::Cluster>* clusters);

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_RECORD_CODEC_H_
