#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <functional>
#include <map>
#include <random>
#include <string>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>

#include "services/engine/memory_engine.h"

#if __has_include(<malloc.h>)
#include <malloc.h>
#endif

#include "absl/cleanup/cleanup.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/feature_space.h"
#include "services/core/static_memory.h"
#include "services/core/validation.h"
#include "services/engine/memory_engine_fleet.h"
#include "services/engine/trace_handles.h"

namespace fleetmem::engine {

namespace {

bool IsFinitePlace(const core::Place& place) {
  return std::isfinite(place.x) && std::isfinite(place.y) &&
         std::isfinite(place.z) && std::isfinite(place.yaw);
}

double PlaceDistance(const core::Place& a, const core::Place& b) {
  const double dx = a.x - b.x;
  const double dy = a.y - b.y;
  const double dz = a.z - b.z;
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

// The query's own fields (not those the fleet decides: the dimension).
absl::Status ValidateQuery(const PlaceQuery& query, size_t max_k) {
  absl::Status status = core::ValidateCode("code", query.code);
  if (!status.ok()) return status;
  if (query.k > max_k) {
    return absl::InvalidArgumentError(
        absl::StrCat("k is ", query.k, " but must be at most ", max_k));
  }
  if (!std::isfinite(query.radius_m)) {
    return absl::InvalidArgumentError("radius_m must be finite");
  }
  if (query.radius_m > 0.0 && !IsFinitePlace(query.near)) {
    return absl::InvalidArgumentError("near must have finite coordinates");
  }
  return core::ValidateReadFilter("filter", query.filter);
}

}  // namespace

FleetStats MemoryEngine::Fleet::Stats() const {
  FleetStats stats;
  stats.traces = memory.trace_count();
  stats.clusters = memory.clusters().size();
  stats.code_dimension = meta.code_dimension;
  stats.encoder_version = meta.encoder_version;
  stats.last_event_id = meta.next_event_id - 1;
  stats.consolidations = meta.consolidations;
  stats.clusters_forgotten = meta.clusters_forgotten;
  stats.first_event_id = std::max<uint64_t>(1, meta.first_event_id);
  stats.quota_rejections = engine->quota_->Rejections(id);
  stats.unindexed_codes = index.get() != nullptr ? index.get()->unindexed() : 0;
  stats.max_clusters = static_cast<uint32_t>(memory.options().max_clusters);
  stats.max_traces_per_cluster =
      static_cast<uint32_t>(memory.options().max_traces_per_cluster);

  std::map<std::string, RobotStats> by_robot;
  std::map<std::string, DomainStats> by_domain;
  auto robot_stats = [&](const std::string& robot_id) -> RobotStats& {
    RobotStats& robot = by_robot[robot_id];
    robot.robot_id = robot_id;
    return robot;
  };
  auto domain_stats = [&](const std::string& domain) -> DomainStats& {
    DomainStats& entry = by_domain[domain];
    entry.domain = domain;
    return entry;
  };
  for (const auto& [robot_id, record] : robots) {
    RobotStats& robot = robot_stats(robot_id);
    robot.max_seq = record.received.max();
    robot.received = record.received.size();
    robot.replayed = record.replayed;
  }
  // O(robots + domains): the counts are kept up to date by every change.
  for (const auto& [robot_id, count] : memory.traces_by_robot()) {
    robot_stats(robot_id).traces = count;
  }
  for (const auto& [domain, count] : memory.traces_by_domain()) {
    domain_stats(domain).traces = count;
  }
  for (const auto& [robot_id, traces] : pending.by_robot()) {
    stats.pending_traces += traces.size();
    robot_stats(robot_id).pending_traces += traces.size();
  }
  for (const auto& [domain, count] : pending.by_domain()) {
    domain_stats(domain).pending_traces = count;
  }
  for (auto& [robot_id, robot] : by_robot) {
    stats.robots.push_back(std::move(robot));
  }
  for (auto& [domain, entry] : by_domain) {
    stats.domains.push_back(std::move(entry));
  }
  return stats;
}

absl::StatusOr<std::vector<PlaceMatch>> MemoryEngine::Fleet::MatchesOf(
    std::span<const Neighbor> neighbors, std::vector<std::vector<float>>& codes,
    size_t k, size_t max_read_bytes) const {
  const bool with_codes = codes.size() == neighbors.size();
  std::vector<core::MemoryTrace> found;
  std::vector<float> distances;
  // The matches' traces, counted against max_read_bytes before any is
  // copied: a query changes nothing, so it is refused whole.
  std::vector<std::pair<const core::MemoryTrace*, size_t>> hits;
  const size_t code_bytes = 4 * size_t{meta.code_dimension};
  size_t bytes = 0;
  for (size_t i = 0; i < neighbors.size(); ++i) {
    const std::optional<core::TraceKey> key = index.KeyOf(neighbors[i].id);
    if (!key.has_value()) continue;
    const core::MemoryTrace* trace = FindTrace(*key);
    if (trace == nullptr) continue;
    hits.emplace_back(trace, i);
    bytes += code_bytes + trace->attachment.size();
  }
  if (bytes > max_read_bytes) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the ", hits.size(), " nearest traces (k ", k, ") hold ", bytes,
        " bytes of codes and attachments, over max_read_bytes ", max_read_bytes,
        "; ask for fewer"));
  }
  found.reserve(hits.size());
  for (const auto& [trace, i] : hits) {
    found.push_back(*trace);
    if (found.back().code.empty() && with_codes) {
      found.back().code = std::move(codes[i]);
    }
    distances.push_back(neighbors[i].distance);
  }
  if (absl::Status filled = FillCodes(found); !filled.ok()) return filled;
  std::vector<PlaceMatch> matches;
  matches.reserve(found.size());
  for (size_t i = 0; i < found.size(); ++i) {
    matches.push_back(PlaceMatch{std::move(found[i]), distances[i]});
  }
  return matches;
}

absl::StatusOr<std::vector<PlaceMatch>> MemoryEngine::QueryPlace(
    std::string_view fleet_id, const PlaceQuery& query) const {
  absl::StatusOr<std::vector<std::vector<PlaceMatch>>> answers =
      QueryPlaces(fleet_id, query, {});
  if (!answers.ok()) return answers.status();
  return std::move(answers->front());
}

namespace {

// QueryPlaces' arguments, before the fleet is read.
absl::Status CheckQueryPlaces(std::string_view fleet_id,
                              const PlaceQuery& query,
                              std::span<const std::vector<float>> more_codes,
                              const EngineOptions& options) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (status.ok()) status = ValidateQuery(query, options.max_query_k);
  if (status.ok() && more_codes.size() + 1 > options.max_query_codes) {
    status = absl::InvalidArgumentError(
        absl::StrCat("codes: ", more_codes.size() + 1, " given; at most ",
                     options.max_query_codes, " per query"));
  }
  for (size_t i = 0; status.ok() && i < more_codes.size(); ++i) {
    status =
        core::ValidateCode(absl::StrCat("codes[", i + 1, "]"), more_codes[i]);
  }
  return status;
}

}  // namespace

absl::StatusOr<std::vector<std::vector<PlaceMatch>>> MemoryEngine::QueryPlaces(
    std::string_view fleet_id, const PlaceQuery& query,
    std::span<const std::vector<float>> more_codes) const {
  const absl::Time start = absl::Now();
  absl::Status status = CheckQueryPlaces(fleet_id, query, more_codes, options_);
  if (!status.ok()) return status;
  const bool use_prior = query.radius_m > 0.0;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);

  std::vector<std::vector<PlaceMatch>> answers;
  {
    absl::ReaderMutexLock lock(&fleet->mu);
    status = fleet->CheckLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    for (size_t i = 0; i <= more_codes.size(); ++i) {
      const std::span<const float> code =
          i == 0 ? std::span<const float>(query.code) : more_codes[i - 1];
      if (code.size() != fleet->meta.code_dimension) {
        return absl::InvalidArgumentError(absl::StrCat(
            i == 0 ? std::string("code") : absl::StrCat("codes[", i, "]"),
            " has dimension ", code.size(), " but fleet \"", V(fleet_id),
            "\" uses ", fleet->meta.code_dimension));
      }
    }
    if (fleet->index.get() == nullptr) {
      return absl::InternalError(
          absl::StrCat("fleet \"", V(fleet_id), "\" has no index"));
    }
    SearchParams params;
    params.k = std::max<size_t>(query.k, 1);
    params.unit_query = true;  // as the codes were added (AddNormalized)
    const bool use_filter = !query.filter.selects_all();
    if (use_prior || use_filter) {
      params.accept = [fleet, &query, use_prior, use_filter](uint64_t handle) {
        const std::optional<core::TraceKey> key = fleet->index.KeyOf(handle);
        if (!key.has_value()) return false;
        const core::MemoryTrace* trace = fleet->FindTrace(*key);
        return trace != nullptr &&
               (!use_prior ||
                PlaceDistance(trace->place, query.near) <= query.radius_m) &&
               (!use_filter || query.filter.Matches(*trace));
      };
    }
    // The codes' answers share one max_read_bytes, so that a call of many
    // codes holds no more than one of one code may.
    size_t budget = options_.max_read_bytes;
    for (size_t i = 0; i <= more_codes.size(); ++i) {
      const std::span<const float> code =
          i == 0 ? std::span<const float>(query.code) : more_codes[i - 1];
      std::vector<std::vector<float>> codes;  // the index's, where it can
      params.codes = &codes;
      absl::StatusOr<std::vector<Neighbor>> neighbors =
          fleet->index.get()->Search(code, params);
      if (!neighbors.ok() && fleet->index.get()->Damaged()) {
        return absl::DataLossError(absl::StrCat(
            neighbors.status().message(),
            "; the fleet's index is rebuilt from the store's codes at its "
            "next write or index snapshot"));
      }
      if (!neighbors.ok()) return neighbors.status();
      absl::StatusOr<std::vector<PlaceMatch>> found =
          fleet->MatchesOf(*neighbors, codes, query.k, budget);
      if (!found.ok()) return found.status();
      for (const PlaceMatch& match : *found) {
        budget -= std::min(budget, 4 * match.trace.code.size() +
                                       match.trace.attachment.size());
      }
      answers.push_back(*std::move(found));
    }
  }
  if (hooks_.on_query) {
    hooks_.on_query(fleet_id, absl::ToDoubleSeconds(absl::Now() - start));
  }
  return answers;
}

absl::StatusOr<FleetStats> MemoryEngine::GetStats(
    std::string_view fleet_id) const {
  return Fleet::ReadExisting(
      *this, fleet_id, [](const Fleet& fleet) -> absl::StatusOr<FleetStats> {
        return fleet.Stats();
      });
}

absl::StatusOr<uint64_t> MemoryEngine::LogPosition(
    std::string_view fleet_id) const {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  // A deleted fleet keeps its position (the delete's entry), not existing.
  const Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return 0;
  absl::ReaderMutexLock lock(&fleet->mu);
  status = fleet->CheckLoaded();
  if (!status.ok()) return status;
  return fleet->meta.log_position;
}

absl::Status CheckTraces(std::string_view fleet_id,
                         std::span<const core::MemoryTrace> traces,
                         const FleetShape* shape, size_t max_traces) {
  if (shape == nullptr) {
    return ValidateUpload(fleet_id, traces, nullptr, max_traces);
  }
  FleetMeta meta;
  meta.code_dimension = shape->code_dimension;
  meta.encoder_version = shape->encoder_version;
  return ValidateUpload(fleet_id, traces, &meta, max_traces);
}

std::optional<FleetShape> MemoryEngine::Shape(std::string_view fleet_id) const {
  const Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return std::nullopt;
  absl::ReaderMutexLock lock(&fleet->mu);
  if (!fleet->exists()) return std::nullopt;
  return FleetShape{fleet->meta.code_dimension, fleet->meta.encoder_version};
}

uint64_t MemoryEngine::HeldTraces(std::string_view fleet_id) const {
  const Fleet* fleet = Fleet::Find(*this, fleet_id);
  return fleet == nullptr ? 0 : fleet->held.load(std::memory_order_relaxed);
}

core::SeqSet MemoryEngine::Received(std::string_view fleet_id,
                                    std::string_view robot_id) const {
  const Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return {};
  absl::ReaderMutexLock lock(&fleet->mu);
  auto it = fleet->robots.find(robot_id);
  return it == fleet->robots.end() ? core::SeqSet() : it->second.received;
}

absl::Status MemoryEngine::CheckFleetExists(std::string_view fleet_id) const {
  return Fleet::ReadExisting(
             *this, fleet_id,
             [](const Fleet&) -> absl::StatusOr<bool> { return true; })
      .status();
}

absl::StatusOr<std::vector<core::MemoryEvent>> MemoryEngine::ReadEvents(
    std::string_view fleet_id, uint64_t after_event) const {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return std::vector<core::MemoryEvent>();
  auto erased = [&](uint64_t first) {
    return absl::OutOfRangeError(absl::StrCat(
        "events ", after_event + 1, "..", first - 1, " of fleet \"",
        V(fleet_id), "\" were erased by the retention bound (",
        options_.max_events_per_fleet,
        " events, max_events_per_fleet); the oldest kept is ", first,
        ": re-read the fleet's state (GetStats, queries) and watch again from "
        "after_event 0"));
  };
  absl::ReaderMutexLock lock(&fleet->mu);
  const uint64_t first = std::max<uint64_t>(1, fleet->meta.first_event_id);
  if (after_event > 0 && after_event < first - 1) return erased(first);
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      store_->ReadEvents(fleet_id, after_event, options_.max_events_per_read);
  // A consolidation's store write (StoreStaged) may erase events beside
  // this reader, before the fleet's meta says so: event ids have no holes,
  // so a first event past after_event + 1 means the rest was erased.
  if (events.ok() && after_event > 0 && !events->empty() &&
      events->front().id - 1 > after_event) {
    return erased(events->front().id);
  }
  return events;
}

std::vector<std::string> MemoryEngine::ListFleets() const {
  std::vector<const Fleet*> fleets;
  {
    absl::ReaderMutexLock lock(&fleets_mu_);
    for (const auto& [fleet_id, fleet] : fleets_) fleets.push_back(fleet.get());
  }
  std::vector<std::string> fleet_ids;
  for (const Fleet* fleet : fleets) {
    absl::ReaderMutexLock lock(&fleet->mu);
    if (fleet->exists()) fleet_ids.push_back(fleet->id);
  }
  std::sort(fleet_ids.begin(), fleet_ids.end());
  return fleet_ids;
}

namespace {

TracePlace PlaceOf(const core::MemoryTrace& trace) {
  return TracePlace{trace.robot_id, trace.seq, trace.domain, trace.place,
                    trace.reward};
}

ClusterSummary Summarize(const core::Cluster& cluster, bool include_places) {
  const core::MemoryEvent described =
      core::DescribeCluster(cluster, core::EventType::kClusterAdded);
  ClusterSummary summary;
  summary.cluster_id = cluster.id;
  summary.robot_id = cluster.robot_id;
  summary.trace_count = described.trace_count;
  summary.centroid_place = described.centroid_place;
  summary.mean_reward = described.mean_reward;
  for (const core::MemoryTrace& trace : cluster.traces) {
    ++summary.robots[trace.robot_id];
    ++summary.domains[trace.domain];
    if (include_places) summary.places.push_back(PlaceOf(trace));
  }
  return summary;
}

}  // namespace

absl::StatusOr<ClusterListing> MemoryEngine::ListClusters(
    std::string_view fleet_id, bool include_places) const {
  return Fleet::ReadExisting(
      *this, fleet_id,
      [include_places](const Fleet& fleet) -> absl::StatusOr<ClusterListing> {
        ClusterListing listing;
        listing.clusters.reserve(fleet.memory.clusters().size());
        for (const auto& [cluster_id, cluster] : fleet.memory.clusters()) {
          listing.clusters.push_back(Summarize(cluster, include_places));
        }
        if (!include_places) return listing;
        for (const auto& [robot_id, traces] : fleet.pending.by_robot()) {
          for (const core::MemoryTrace& trace : traces) {
            listing.pending.push_back(PlaceOf(trace));
          }
        }
        return listing;
      });
}

absl::StatusOr<TracePage> MemoryEngine::ListTraces(
    std::string_view fleet_id, const std::optional<core::TraceKey>& after,
    size_t page_size) const {
  if (page_size == 0) {
    return absl::InvalidArgumentError("page_size: must be at least 1");
  }
  return Fleet::ReadExisting(
      *this, fleet_id, [&](const Fleet& fleet) -> absl::StatusOr<TracePage> {
        // Every trace after the cursor; then the page's first ones by key.
        std::vector<const core::MemoryTrace*> candidates;
        TracePage page;
        auto consider = [&](const std::vector<core::MemoryTrace>& traces) {
          page.total += traces.size();
          for (const core::MemoryTrace& trace : traces) {
            if (!after.has_value() || *after < trace.key()) {
              candidates.push_back(&trace);
            }
          }
        };
        for (const auto& [cluster_id, cluster] : fleet.memory.clusters()) {
          consider(cluster.traces);
        }
        for (const auto& [robot_id, traces] : fleet.pending.by_robot())
          consider(traces);
        const size_t taken = std::min(page_size, candidates.size());
        std::partial_sort(
            candidates.begin(), candidates.begin() + taken, candidates.end(),
            [](const core::MemoryTrace* a, const core::MemoryTrace* b) {
              return std::tie(a->robot_id, a->seq) <
                     std::tie(b->robot_id, b->seq);
            });
        // Then as many of them as max_read_bytes holds (at least one).
        const size_t code_bytes = 4 * size_t{fleet.meta.code_dimension};
        size_t bytes = 0;
        for (size_t i = 0; i < taken; ++i) {
          bytes += code_bytes + candidates[i]->attachment.size();
          if (i > 0 && bytes > options_.max_read_bytes) break;
          page.traces.push_back(*candidates[i]);
        }
        absl::Status filled = fleet.FillCodes(page.traces);
        if (!filled.ok()) return filled;
        page.more = candidates.size() > page.traces.size();
        return page;
      });
}

}  // namespace fleetmem::engine
