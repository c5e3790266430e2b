#include "services/storage/fleet_image.h"

#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"
#include "services/storage/keys.h"
#include "services/storage/mutation_checks.h"
#include "services/storage/record_codec.h"
#include "services/storage/records.pb.h"

namespace fleetmem::storage {
namespace {

constexpr std::string_view kImageFormat = "fleetmem.fleet-image/1";

void Add(std::string key, std::string value, FleetImage* image) {
  ImageRecord* record = image->add_records();
  record->set_key(std::move(key));
  record->set_value(std::move(value));
}

template <typename T>
absl::Status AppendTo(absl::StatusOr<T> value, std::vector<T>* out) {
  if (!value.ok()) return value.status();
  out->push_back(*std::move(value));
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::string> EncodeFleetImage(const engine::FleetImage& image) {
  const engine::FleetRecord& fleet = image.record;
  const std::string& id = fleet.fleet_id;
  if (absl::Status status = internal::CheckFleetId(id); !status.ok()) {
    return status;
  }
  FleetImage out;
  out.set_format(std::string(kImageFormat));
  out.set_fleet_id(id);
  Add(keys::MetaKey(id), EncodeMeta(fleet.meta), &out);
  for (const core::MemoryTrace& trace : fleet.pending) {
    Add(keys::PendingKey(id, trace.key()), EncodeTrace(trace), &out);
  }
  for (const core::Cluster& cluster : fleet.clusters) {
    StoredCluster stored{cluster.id, cluster.robot_id, cluster.centroid, {}};
    stored.members.reserve(cluster.traces.size());
    for (const core::MemoryTrace& trace : cluster.traces) {
      stored.members.push_back(trace.key());
      Add(keys::TraceKey(id, trace.key()), EncodeTrace(trace), &out);
    }
    Add(keys::ClusterKey(id, cluster.id), EncodeCluster(stored), &out);
  }
  for (const engine::RobotRecord& robot : fleet.robots) {
    Add(keys::RobotKey(id, robot.robot_id), EncodeRobot(robot), &out);
  }
  for (const core::MemoryEvent& event : image.events) {
    Add(keys::EventKey(id, event.id), EncodeEvent(event), &out);
  }
  return out.SerializeAsString();
}

namespace {

// A fleet image as its records are decoded: clusters are assembled once
// every trace is read, so their records wait here.
struct DecodedImage {
  engine::FleetImage image;
  TraceTable traces;
  std::vector<std::pair<std::string_view, StoredCluster>> clusters;
  bool has_meta = false;
};

// Decodes one record of the image (of `tag`) into `out`.
absl::Status DecodeImageRecord(std::string_view fleet_id, keys::Tag tag,
                               const ImageRecord& record, DecodedImage& out) {
  switch (tag) {
    case keys::Tag::kMeta: {
      absl::StatusOr<engine::FleetMeta> meta =
          DecodeMeta(record.key(), record.value());
      if (meta.ok()) out.image.record.meta = *std::move(meta);
      out.has_meta = true;
      return meta.status();
    }
    case keys::Tag::kPending:
      return AppendTo(DecodeTrace(record.key(), record.value()),
                      &out.image.record.pending);
    case keys::Tag::kTrace: {
      absl::StatusOr<core::MemoryTrace> trace =
          DecodeTrace(record.key(), record.value());
      if (!trace.ok()) return trace.status();
      // An image is whole: a store given a trace without its code would
      // keep the one it holds (engine::FleetMutation::put_clusters).
      if (trace->code.empty()) {
        return absl::DataLossError(
            absl::StrCat("fleet image of \"", V(fleet_id), "\": record ",
                         keys::Describe(record.key()), " has no code"));
      }
      out.traces.Add(*std::move(trace));
      return absl::OkStatus();
    }
    case keys::Tag::kCluster: {
      absl::StatusOr<StoredCluster> cluster =
          DecodeCluster(record.key(), record.value());
      if (cluster.ok()) out.clusters.emplace_back(record.key(), *cluster);
      return cluster.status();
    }
    case keys::Tag::kRobot:
      return AppendTo(DecodeRobot(record.key(), record.value()),
                      &out.image.record.robots);
    case keys::Tag::kEvent:
      return AppendTo(DecodeEvent(record.key(), record.value()),
                      &out.image.events);
    case keys::Tag::kLog:
      return absl::DataLossError(
          absl::StrCat("fleet image of \"", V(fleet_id), "\": record ",
                       keys::Describe(record.key()),
                       " is an ingest-log entry, which no image holds"));
  }
  return absl::DataLossError(
      absl::StrCat("fleet image of \"", V(fleet_id), "\": record ",
                   keys::Describe(record.key()), " is of an unknown kind"));
}

}  // namespace

absl::StatusOr<engine::FleetImage> DecodeFleetImage(std::string_view fleet_id,
                                                    std::string_view bytes) {
  FleetImage in;
  if (!in.ParseFromArray(bytes.data(), static_cast<int>(bytes.size())) ||
      in.format() != kImageFormat) {
    return absl::DataLossError(absl::StrCat("fleet image of \"", V(fleet_id),
                                            "\": not a fleet image of format ",
                                            V(kImageFormat)));
  }
  if (in.fleet_id() != fleet_id) {
    return absl::DataLossError(absl::StrCat("fleet image of \"", V(fleet_id),
                                            "\" holds fleet \"", in.fleet_id(),
                                            "\""));
  }
  DecodedImage decoded;
  decoded.image.record.fleet_id = std::string(fleet_id);
  for (const ImageRecord& record : in.records()) {
    const std::optional<keys::ParsedKey> key = keys::Parse(record.key());
    if (!key || key->fleet_id != fleet_id) {
      return absl::DataLossError(absl::StrCat(
          "fleet image of \"", V(fleet_id), "\": record ",
          keys::Describe(record.key()), " is not one of this fleet"));
    }
    if (absl::Status status =
            DecodeImageRecord(fleet_id, key->tag, record, decoded);
        !status.ok()) {
      return status;
    }
  }
  if (!decoded.has_meta) {
    return absl::DataLossError(absl::StrCat("fleet image of \"", V(fleet_id),
                                            "\" has no meta record"));
  }
  for (auto& [key, stored] : decoded.clusters) {
    if (absl::Status status =
            AssembleCluster(key, std::move(stored), &decoded.traces,
                            &decoded.image.record.clusters);
        !status.ok()) {
      return status;
    }
  }
  if (const core::MemoryTrace* orphan = decoded.traces.AnyLeft()) {
    return absl::DataLossError(absl::StrCat(
        "fleet image of \"", V(fleet_id), "\": trace ", orphan->robot_id, "/",
        orphan->seq, " belongs to no cluster"));
  }
  return std::move(decoded.image);
}

}  // namespace fleetmem::storage
