#include "services/storage/testing/store_test_util.h"

#include <stdlib.h>

#include <cstdlib>
#include <filesystem>
#include <map>
#include <stdexcept>

#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"

namespace fleetmem::storage::testing {
namespace {

void DumpPlace(const core::Place& p, std::string* out) {
  absl::StrAppendFormat(out, "(%a,%a,%a,%a)", p.x, p.y, p.z, p.yaw);
}

void DumpFloats(const std::vector<float>& values, std::string* out) {
  out->append("[");
  for (float v : values) absl::StrAppendFormat(out, "%a,", v);
  out->append("]");
}

void DumpTrace(const core::MemoryTrace& t, std::string* out) {
  absl::StrAppend(out, "    trace ", t.robot_id, "/", t.seq,
                  " domain=", t.domain, " cluster=", t.cluster_id,
                  " replay=", t.replay_count, " ts=", t.timestamp_ns,
                  " enc=", t.encoder_version,
                  " attachment=", absl::CHexEscape(t.attachment));
  absl::StrAppendFormat(out, " reward=%a ex=%a in=%a place=", t.reward,
                        t.reward_external, t.reward_internal);
  DumpPlace(t.place, out);
  out->append(" code=");
  DumpFloats(t.code, out);
  out->append("\n");
}

}  // namespace

core::MemoryTrace MakeTrace(const std::string& robot_id, uint64_t seq) {
  core::MemoryTrace trace;
  trace.robot_id = robot_id;
  trace.seq = seq;
  trace.domain = seq % 2 == 0 ? "summer" : "winter";
  const float base = static_cast<float>(seq) + 0.1f * robot_id.size();
  trace.code = {base, -base / 3.0f, 0.5f, 1e-7f * base};
  trace.place = core::Place{10.0 * seq, -2.5 * seq, 0.125, 0.01 * seq};
  trace.reward = 0.25f + 0.01f * seq;
  trace.reward_external = 0.2f;
  trace.reward_internal = 0.05f + 0.01f * seq;
  trace.timestamp_ns = 1'700'000'000'000'000'000 + static_cast<int64_t>(seq);
  trace.encoder_version = "netvlad-1";
  // Bytes of any value (a scan), every third trace.
  if (seq % 3 == 0) trace.attachment = std::string("\0\x01scan\xff", 7);
  return trace;
}

core::Cluster MakeCluster(uint64_t id, const std::string& robot_id,
                          const std::vector<uint64_t>& seqs) {
  core::Cluster cluster;
  cluster.id = id;
  cluster.robot_id = robot_id;
  cluster.centroid = {static_cast<float>(id), 0.5f, -1.0f / 3.0f};
  for (uint64_t seq : seqs) {
    core::MemoryTrace trace = MakeTrace(robot_id, seq);
    trace.cluster_id = id;
    cluster.traces.push_back(std::move(trace));
  }
  return cluster;
}

core::MemoryEvent MakeEvent(uint64_t id, core::EventType type,
                            uint64_t cluster_id) {
  core::MemoryEvent event;
  event.id = id;
  event.type = type;
  event.cluster_id = cluster_id;
  event.trace_count = static_cast<uint32_t>(3 + id);
  event.robot_id = absl::StrCat("r", id % 3);
  event.domain = "night";
  event.centroid_place = core::Place{1.5 * id, 2.0, -3.0, 0.0};
  event.mean_reward = 0.5f + 0.125f * id;
  event.timestamp_ns = 1'000 * static_cast<int64_t>(id);
  return event;
}

engine::RobotRecord MakeRobot(const std::string& robot_id,
                              const std::vector<core::SeqSet::Interval>& seqs,
                              uint64_t replayed) {
  engine::RobotRecord robot;
  robot.robot_id = robot_id;
  robot.received = core::SeqSet::FromIntervals(seqs);
  robot.replayed = replayed;
  return robot;
}

engine::FleetMeta MakeMeta(uint64_t consolidations) {
  engine::FleetMeta meta;
  meta.code_dimension = 4;
  meta.encoder_version = "netvlad-1";
  meta.next_cluster_id = 10 + consolidations;
  meta.next_event_id = 20 + consolidations;
  meta.consolidations = consolidations;
  meta.clusters_forgotten = consolidations / 2;
  meta.log_position = 30 + consolidations;
  // Own settings: the index's among them (every field is stored).
  engine::FleetSettings settings;
  settings.place_unit = "m";
  settings.index.kind = engine::IndexSettings::Kind::kAuto;
  settings.index.hnsw_m = 12;
  settings.index.hnsw_ef_search = 64;
  settings.index.hnsw_codes = engine::IndexSettings::Codes::kFloat;
  meta.settings = settings;
  return meta;
}

std::string Dump(const engine::FleetRecord& record) {
  const engine::FleetMeta& m = record.meta;
  std::string out = absl::StrCat(
      "fleet ", record.fleet_id, "\nmeta dim=", m.code_dimension,
      " enc=", m.encoder_version, " next_cluster=", m.next_cluster_id,
      " next_event=", m.next_event_id, " consolidations=", m.consolidations,
      " forgotten=", m.clusters_forgotten, " log_position=", m.log_position,
      "\nsettings ", m.settings.has_value());
  if (m.settings.has_value()) {
    const engine::IndexSettings& index = m.settings->index;
    absl::StrAppend(&out, " unit=", m.settings->place_unit,
                    " index=", static_cast<int>(index.kind),
                    " m=", index.hnsw_m, " ef=", index.hnsw_ef_search,
                    " codes=", static_cast<int>(index.hnsw_codes));
  }
  out.append("\npending\n");
  for (const core::MemoryTrace& trace : record.pending) DumpTrace(trace, &out);
  for (const core::Cluster& cluster : record.clusters) {
    absl::StrAppend(&out, "cluster ", cluster.id, " robot=", cluster.robot_id,
                    " centroid=");
    DumpFloats(cluster.centroid, &out);
    out.append("\n");
    for (const core::MemoryTrace& trace : cluster.traces) {
      DumpTrace(trace, &out);
    }
  }
  for (const engine::RobotRecord& robot : record.robots) {
    absl::StrAppend(&out, "robot ", robot.robot_id,
                    " replayed=", robot.replayed,
                    " size=", robot.received.size(), " received=");
    for (const auto& [first, last] : robot.received.Intervals()) {
      absl::StrAppend(&out, "[", first, ",", last, "]");
    }
    out.append("\n");
  }
  return out;
}

std::string Dump(const std::vector<core::MemoryEvent>& events) {
  std::string out;
  for (const core::MemoryEvent& e : events) {
    absl::StrAppend(&out, "event ", e.id, " type=", static_cast<int>(e.type),
                    " cluster=", e.cluster_id, " traces=", e.trace_count,
                    " robot=", e.robot_id, " domain=", e.domain,
                    " ts=", e.timestamp_ns, " into=", e.merged_into,
                    " dropped=", e.traces_dropped);
    absl::StrAppendFormat(&out, " reward=%a place=", e.mean_reward);
    DumpPlace(e.centroid_place, &out);
    out.append("\n");
  }
  return out;
}

std::vector<engine::FleetMutation> ScriptedMutations(int count) {
  std::vector<engine::FleetMutation> mutations;
  std::vector<core::MemoryTrace> pending;
  std::map<uint64_t, core::Cluster> clusters;
  std::map<std::string, engine::RobotRecord> robots;
  engine::FleetMeta meta = MakeMeta(0);
  meta.next_cluster_id = 1;
  meta.next_event_id = 1;
  for (int i = 0; i < count; ++i) {
    engine::FleetMutation m;
    // Upload: three traces of one robot.
    const std::string robot_id = absl::StrCat("r", i % 3);
    engine::RobotRecord& robot = robots[robot_id];
    robot.robot_id = robot_id;
    for (int j = 0; j < 3; ++j) {
      const uint64_t seq = robot.received.max() + 1 + (i % 5 == 0 ? 1 : 0);
      robot.received.Insert(seq);
      pending.push_back(MakeTrace(robot_id, seq));
      m.put_pending.push_back(pending.back());
    }
    m.put_robots.push_back(robot);
    // Consolidation: the four oldest pending traces become a cluster.
    if (i % 3 == 2) {
      core::Cluster cluster;
      cluster.id = meta.next_cluster_id++;
      cluster.robot_id = robot_id;
      cluster.centroid = {static_cast<float>(i), 0.25f};
      for (int j = 0; j < 4; ++j) {
        core::MemoryTrace trace = pending.front();
        pending.erase(pending.begin());
        m.erase_pending.push_back(trace.key());
        trace.cluster_id = cluster.id;
        cluster.traces.push_back(std::move(trace));
      }
      ++meta.consolidations;
      m.append_events.push_back(MakeEvent(
          meta.next_event_id++, core::EventType::kClusterAdded, cluster.id));
      clusters[cluster.id] = cluster;
      m.put_clusters.push_back(std::move(cluster));
    }
    // Replay: one trace of each of the two newest clusters is handed out.
    if (i % 4 == 3) {
      int updated = 0;
      for (auto it = clusters.rbegin(); it != clusters.rend() && updated < 2;
           ++it, ++updated) {
        core::MemoryTrace& trace = it->second.traces.front();
        ++trace.replay_count;
        m.update_traces.push_back(trace);
        // Every other update without its code, as a reward update is
        // written (the store keeps the code).
        if (updated == 1) m.update_traces.back().code.clear();
        ++robot.replayed;
      }
      m.put_robots.back() = robot;
    }
    // Forgetting: the oldest cluster goes once there are more than three.
    if (i % 7 == 6 && clusters.size() > 3) {
      const uint64_t id = clusters.begin()->first;
      clusters.erase(clusters.begin());
      m.erase_clusters.push_back(id);
      ++meta.clusters_forgotten;
      m.append_events.push_back(MakeEvent(
          meta.next_event_id++, core::EventType::kClusterForgotten, id));
    }
    // Forgetting by merging: the oldest cluster goes into the next oldest,
    // put with the traces of both and none of their codes, as the engine
    // writes a merge (the store keeps the codes it holds).
    if (i % 13 == 12 && clusters.size() > 2) {
      core::Cluster from = clusters.begin()->second;
      clusters.erase(clusters.begin());
      core::Cluster& into = clusters.begin()->second;
      for (core::MemoryTrace& trace : from.traces) {
        trace.cluster_id = into.id;
        into.traces.push_back(std::move(trace));
      }
      into.centroid[1] += 1.0f;
      m.erase_clusters.push_back(from.id);
      core::Cluster& put = m.put_clusters.emplace_back(into);
      for (core::MemoryTrace& trace : put.traces) trace.code.clear();
      ++meta.clusters_forgotten;
      m.append_events.push_back(MakeEvent(
          meta.next_event_id++, core::EventType::kClusterMerged, from.id));
    }
    // A single trace leaves the newest cluster.
    if (i % 11 == 10 && !clusters.empty()) {
      std::vector<core::MemoryTrace>& traces = clusters.rbegin()->second.traces;
      if (traces.size() > 1) {
        m.erase_traces.push_back(traces.back().key());
        traces.pop_back();
      }
    }
    m.put_meta = true;
    m.meta = meta;
    mutations.push_back(std::move(m));
  }
  return mutations;
}

}  // namespace fleetmem::storage::testing
