#include "clients/robot/runtime/agent.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <thread>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "clients/robot/runtime/fleet_recall.h"
#include "clients/robot/sensing/code_search.h"
#include "google/protobuf/util/json_util.h"
#include "proto/convert/trace_convert.h"
#include "services/core/place_metrics.h"
#include "services/core/validation.h"

namespace fleetmem::robot {
namespace {

using Clock = std::chrono::steady_clock;

using api::PlaceFromProto;
using api::TraceFromProto;

// A learner's one-line report as a log line's tail ("" without one).
std::string Reported(const std::string& report) {
  return report.empty() ? "" : absl::StrCat("; learner: ", report);
}

// Why a first robot scores 0: what the fleet held for its queries was only
// its own earlier traces, never the place it stood at.
std::string OwnOnlyNote(uint64_t own_only, size_t scored) {
  if (own_only == 0) return "";
  if (own_only >= scored) {
    return " (every answer was one of its own earlier traces: the fleet had "
           "nothing of these places to relocalise against)";
  }
  return absl::StrFormat(
      " (%d of them answered only with its own earlier traces: nothing of "
      "those places from the fleet)",
      own_only);
}

}  // namespace

absl::StatusOr<float> InternalRewardOf(const Encoder& encoder,
                                       const Observation& observation,
                                       std::span<const float> code,
                                       uint64_t seed, size_t index) {
  std::mt19937_64 perturb_rng(seed * 1000003u + index);
  absl::StatusOr<Observation> moved = encoder.Perturb(observation, perturb_rng);
  if (!moved.ok()) return moved.status();
  absl::StatusOr<std::vector<float>> moved_code = encoder.Encode(*moved);
  if (!moved_code.ok()) return moved_code.status();
  return InternalReward(code, *moved_code);
}

bool IsRetryable(absl::StatusCode code) {
  return code == absl::StatusCode::kUnavailable ||
         code == absl::StatusCode::kDeadlineExceeded ||
         code == absl::StatusCode::kResourceExhausted ||
         code == absl::StatusCode::kAborted;
}

Agent::Agent(AgentOptions options, client::Client* client,
             client::Client* query_client, const ObservationSource* source,
             const Encoder* encoder, RobotStore* store, Learner* learner,
             ObservationHook* hook)
    : options_(std::move(options)),
      client_(client),
      query_client_(query_client),
      source_(source),
      encoder_(encoder),
      store_(store),
      learner_(learner),
      hook_(hook),
      memory_(options_.robot_id, options_.dynamic_memory),
      rng_(options_.seed),
      window_(options_.sequence.length) {
  end_ = std::min(options_.last, source_->size());
}

Agent::~Agent() = default;

void Agent::Log(const std::string& line) const {
  const std::string text = absl::StrCat("[", options_.robot_id, "] ", line);
  if (options_.log) {
    options_.log(text);
  } else {
    std::cerr << text << std::endl;
  }
}

absl::Status Agent::fatal() const {
  absl::MutexLock lock(&mu_);
  return fatal_;
}

void Agent::SetFatal(absl::Status status) {
  absl::MutexLock lock(&mu_);
  if (fatal_.ok()) fatal_ = std::move(status);
  last_error_ = fatal_.ToString();
}

void Agent::SleepUnless(std::chrono::milliseconds duration,
                        const std::atomic<bool>& stop) {
  const auto until = Clock::now() + duration;
  while (!stop.load() && Clock::now() < until) {
    std::this_thread::sleep_for(std::min<Clock::duration>(
        std::chrono::milliseconds(50), until - Clock::now()));
  }
}

AgentSummary Agent::summary() const {
  AgentSummary summary;
  summary.state = store_->state();
  summary.queue = store_->queue();
  summary.observed_this_run = observed_this_run_;
  summary.source_finished = source_finished_;
  summary.drained = drained_;
  return summary;
}

absl::StatusOr<size_t> Agent::StartPosition() {
  const RobotState start = store_->state();
  const size_t index = std::max<size_t>(start.next_index(), options_.first);
  if (start.next_index() > options_.first && start.observations() > 0) {
    Log(absl::StrFormat(
        "resuming at observation %d of %s (%d observed before, %d open, "
        "%d queued, next seq %d)",
        index, source_->description(), start.observations(),
        store_->queue().open_segment, store_->queue().depth, start.next_seq()));
  }
  if (index != start.next_index()) {
    // First run with --first beyond 0: the position starts there.
    absl::Status moved = store_->Update(
        [index](RobotState& state) { state.set_next_index(index); });
    if (!moved.ok()) return moved;
  }
  return index;
}

void Agent::Pace(Clock::time_point run_start, const std::atomic<bool>& stop) {
  if (options_.rate_hz <= 0.0) return;
  const auto due =
      run_start +
      std::chrono::duration_cast<Clock::duration>(
          std::chrono::duration<double>(observed_this_run_ / options_.rate_hz));
  if (due > Clock::now()) {
    SleepUnless(std::chrono::duration_cast<std::chrono::milliseconds>(
                    due - Clock::now()),
                stop);
  }
}

void Agent::Drain(const std::atomic<bool>& stop) {
  phase_ = "draining";
  const auto deadline = Clock::now() + options_.drain_timeout;
  while (store_->queue().depth > 0 && Clock::now() < deadline && !stop.load() &&
         fatal().ok()) {
    WriteStatus(phase_, false);
    Progress(false);
    SleepUnless(std::chrono::milliseconds(100), stop);
  }
  drained_ = store_->queue().depth == 0;
  if (!drained_) {
    Log(absl::StrFormat(
        "the queue still holds %d traces (oldest %.1f s); they stay in the "
        "data dir and are uploaded at the next start",
        store_->queue().depth,
        store_->queue().oldest_stored_unix_ns == 0
            ? 0.0
            : (absl::ToUnixNanos(absl::Now()) -
               store_->queue().oldest_stored_unix_ns) /
                  1e9));
  }
}

absl::Status Agent::Run(const std::atomic<bool>& stop) {
  std::thread uploader;
  std::thread watcher;
  if (options_.upload) uploader = std::thread([this] { UploadLoop(); });
  watcher = std::thread([this] { WatchLoop(); });
  auto join = [&] {
    stop_threads_ = true;
    if (uploader.joinable()) uploader.join();
    watcher.join();
  };
  absl::StatusOr<size_t> start = StartPosition();
  if (!start.ok()) {
    join();
    return start.status();
  }
  size_t index = *start;
  // Start with the fleet's memory: a restarted robot's M_D is empty.
  Refresh();
  phase_ = "observing";
  const auto run_start = Clock::now();
  absl::Status status;
  // A new robot learns from its peers' traces before its first frame; its
  // learner failing stops it as at a segment's end.
  if (learner_ != nullptr && options_.warm_start &&
      store_->state().observations() == 0 && DomainCount(memory_) >= 2) {
    absl::StatusOr<std::string> warmed = WarmStart(*learner_, memory_);
    if (warmed.ok()) {
      Log(absl::StrCat("warm start from the ", memory_.size(),
                       " traces of its first refresh: ", *warmed));
    } else {
      status = warmed.status();
    }
  }
  for (; status.ok() && index < end_ && !stop.load(); ++index) {
    Pace(run_start, stop);
    if (stop.load()) break;
    // A refused upload or a failing disk stops the robot at once.
    status = fatal();
    if (!status.ok()) break;
    status = ObserveOne(index, stop);
    if (!status.ok()) break;
    if (store_->queue().open_segment >= options_.segment_size ||
        query_segment_.size() >= options_.segment_size) {
      status = SealSegment();
      if (!status.ok()) break;
    }
    WriteStatus(phase_, false);
    Progress(false);
  }
  if (status.ok() && !stop.load() && index >= end_) {
    source_finished_ = true;
    if (store_->queue().open_segment > 0 || !query_segment_.empty()) {
      status = SealSegment();
    }
  }
  if (status.ok() && stop.load()) {
    phase_ = "stopped";
    Log("stopping: every observation so far is uploaded or durable here");
  }
  if (status.ok() && source_finished_ && options_.upload) Drain(stop);
  if (status.ok()) status = fatal();
  join();
  if (status.ok() && source_finished_) {
    phase_ = drained_ || !options_.upload ? "done" : "undrained";
  } else if (!status.ok()) {
    phase_ = "failed";
    absl::MutexLock lock(&mu_);
    last_error_ = status.ToString();
  }
  WriteStatus(phase_, true);
  Progress(true);
  return status;
}

absl::Status Agent::RecordQuery(size_t index, const Observation& observation,
                                std::vector<float> code,
                                const Relocalisation& relocalisation) {
  // A query-only robot records only its position and its scores.
  absl::Status moved_on = store_->Update([&](RobotState& state) {
    state.set_next_index(index + 1);
    state.set_observations(state.observations() + 1);
    relocalisation.CountIn(state);
  });
  if (!moved_on.ok()) return moved_on;
  ++observed_this_run_;
  core::MemoryTrace& trace = query_segment_.emplace_back();
  trace.robot_id = options_.robot_id;
  trace.domain = options_.domain;
  trace.code = std::move(code);
  trace.place = observation.place;
  trace.encoder_version = encoder_->version();
  query_indices_.push_back(index);
  return absl::OkStatus();
}

absl::Status Agent::Record(size_t index, const v1::MemoryTrace& trace,
                           const Relocalisation& relocalisation,
                           const std::atomic<bool>& stop) {
  auto update = [&relocalisation](RobotState& state) {
    relocalisation.CountIn(state);
  };
  bool told = false;
  while (true) {
    absl::Status recorded = store_->RecordObservation(index, trace, update);
    if (recorded.ok()) break;
    if (recorded.code() != absl::StatusCode::kResourceExhausted) {
      return recorded;
    }
    // Queue full (policy refuse): wait for the uploader. If the open segment
    // alone fills the bound, seal it early so that it can drain.
    if (store_->queue().depth == 0 && store_->queue().open_segment > 0) {
      absl::Status sealed = SealSegment();
      if (!sealed.ok()) return sealed;
      continue;
    }
    if (!told) {
      Log(std::string(recorded.message()));
      told = true;
    }
    phase_ = "queue-full";
    WriteStatus(phase_, false);
    Progress(false);
    if (!fatal().ok()) return fatal();
    SleepUnless(std::chrono::milliseconds(100), stop);
    if (stop.load()) return absl::OkStatus();
  }
  if (told) Log("the queue has room again; observing");
  phase_ = "observing";
  ++observed_this_run_;
  return absl::OkStatus();
}

absl::Status Agent::ObserveOne(size_t index, const std::atomic<bool>& stop) {
  absl::StatusOr<Observation> observation = source_->Read(index);
  if (!observation.ok()) return observation.status();
  absl::StatusOr<std::vector<float>> code = encoder_->Encode(*observation);
  if (!code.ok()) return code.status();
  absl::Status valid =
      core::ValidateCode(absl::StrCat("code of ", observation->name), *code);
  if (!valid.ok()) return valid;
  const Relocalisation relocalisation = Relocalise(*code, observation->place);
  if (!options_.upload) {
    return RecordQuery(index, *observation, *std::move(code), relocalisation);
  }
  absl::StatusOr<float> internal =
      InternalRewardOf(*encoder_, *observation, *code, options_.seed, index);
  if (!internal.ok()) return internal.status();
  v1::MemoryTrace trace;
  trace.set_robot_id(options_.robot_id);
  trace.set_domain(options_.domain);
  trace.mutable_code()->Assign(code->begin(), code->end());
  api::PlaceToProto(observation->place, trace.mutable_pose());
  trace.set_reward_internal(*internal);
  trace.set_timestamp_ns(observation->timestamp_ns != 0
                             ? observation->timestamp_ns
                             : absl::ToUnixNanos(absl::Now()));
  trace.set_encoder_version(encoder_->version());
  if (hook_ != nullptr) {
    absl::Status hooked =
        hook_->BeforeRecord(index, *observation, *code, trace);
    if (!hooked.ok()) return hooked;
  }
  return Record(index, trace, relocalisation, stop);
}

Agent::Relocalisation Agent::Relocalise(const std::vector<float>& code,
                                        const core::Place& place) {
  Relocalisation result;
  if (!options_.relocalise) return result;
  const bool sequence = options_.sequence.length > 1;
  v1::QueryPlaceRequest request;
  request.set_fleet_id(options_.fleet_id);
  request.mutable_code()->Assign(code.begin(), code.end());
  request.set_k(sequence
                    ? std::max(options_.query_k, options_.sequence_candidates)
                    : options_.query_k);
  const auto start = Clock::now();
  absl::StatusOr<std::vector<v1::PlaceMatch>> matches =
      query_client_->QueryPlace(request);
  result.ms =
      std::chrono::duration<double, std::milli>(Clock::now() - start).count();
  std::vector<SequenceCandidate> candidates;
  if (matches.ok()) {
    result.own_only = !matches->empty();
    for (const v1::PlaceMatch& match : *matches) {
      result.own_only =
          result.own_only && match.trace().robot_id() == options_.robot_id;
      candidates.push_back({.place = PlaceFromProto(match.trace().pose()),
                            .distance = match.distance()});
    }
  }
  // Frames without an answer stay in the window as empty ones, so that the
  // distance travelled still adds up.
  if (sequence) window_.Add(place, candidates);
  if (!candidates.empty()) {
    if (!options_.score_relocalisation) {
      result.unscored = true;
      return result;
    }
    const size_t k = std::min<size_t>(options_.query_k, candidates.size());
    std::vector<core::Place> found;
    for (size_t i = 0; i < k; ++i) found.push_back(candidates[i].place);
    result.rank = FirstCorrectRank(found, place, options_.match_radius);
    if (sequence) {
      result.sequence_rank = FirstCorrectRank(
          SequencePlaces(window_.frames(), options_.sequence, k), place,
          options_.match_radius);
    }
  } else if (matches.ok() ||
             matches.status().code() == absl::StatusCode::kNotFound) {
    result.empty = true;  // no memory yet (an unknown fleet is an empty one)
  } else {
    result.unanswered = true;
  }
  return result;
}

void Agent::Relocalisation::CountIn(RobotState& state) const {
  // Adds one to histogram[r] (a rank histogram of RobotState).
  auto count = [](google::protobuf::RepeatedField<uint64_t>& histogram, int r) {
    while (histogram.size() <= r) histogram.Add(0);
    histogram.Set(r, histogram.Get(r) + 1);
  };
  if (rank >= 0) count(*state.mutable_relocalisation_ranks(), rank);
  if (rank >= 0 && own_only) {
    state.set_relocalisation_own_only(state.relocalisation_own_only() + 1);
  }
  if (sequence_rank >= 0) {
    count(*state.mutable_sequence_ranks(), sequence_rank);
  }
  if (unscored) {
    state.set_relocalisation_unscored(state.relocalisation_unscored() + 1);
  }
  if (rank >= 0 || unscored) {
    state.set_relocalisation_ms_total(state.relocalisation_ms_total() + ms);
  }
  if (unanswered) {
    state.set_relocalisation_unanswered(state.relocalisation_unanswered() + 1);
  }
  if (empty) state.set_relocalisation_empty(state.relocalisation_empty() + 1);
}

absl::StatusOr<SegmentStepResult> Agent::StepSegment(
    std::vector<core::MemoryTrace> segment,
    const std::vector<size_t>& indices) {
  std::vector<Observation> observations;
  if (learner_ != nullptr) {
    for (size_t index : indices) {
      absl::StatusOr<Observation> observation = source_->Read(index);
      if (!observation.ok()) return observation.status();
      observations.push_back(*std::move(observation));
    }
  }
  // Recall through the query client (short deadline): a server that does
  // not answer leaves the segment without recalled partners, as a refresh
  // it cannot make leaves M_D as it is.
  absl::Status unanswered;
  const PlaceRecall fleet =
      NewFleetRecall(query_client_, options_.fleet_id, options_.match_radius);
  const PlaceRecall recall =
      [&](const core::MemoryTrace& observed,
          size_t k) -> absl::StatusOr<std::vector<core::MemoryTrace>> {
    absl::StatusOr<std::vector<core::MemoryTrace>> recalled =
        fleet(observed, k);
    if (recalled.ok() || absl::IsNotFound(recalled.status())) return recalled;
    unanswered = recalled.status();
    return absl::NotFoundError("recall unanswered");  // stops recall
  };
  // Recalled traces feed the learner only: without one, no queries.
  absl::StatusOr<SegmentStepResult> step = RunSegmentStep(
      options_.step, std::move(segment), observations, memory_, rng_, learner_,
      learner_ != nullptr ? recall : PlaceRecall());
  if (!unanswered.ok()) {
    Log(absl::StrCat("place recall skipped for this segment (",
                     unanswered.ToString(), ")"));
  }
  return step;
}

absl::Status Agent::SealSegment() {
  if (!options_.upload) {
    // A query-only robot still replays, learns and refreshes per segment.
    absl::StatusOr<SegmentStepResult> step =
        StepSegment(std::move(query_segment_), query_indices_);
    query_segment_.clear();
    query_indices_.clear();
    if (!step.ok()) return step.status();
    absl::Status counted = store_->Update([&](RobotState& state) {
      state.set_segments(state.segments() + 1);
      state.set_replayed_own(state.replayed_own() + step->replayed_own);
      state.set_replayed_peer(state.replayed_peer() + step->replayed_peer);
    });
    if (!counted.ok()) return counted;
    Log(absl::StrFormat("segment %d: replayed %d traces (%d of peers)%s",
                        store_->state().segments(),
                        step->replayed_own + step->replayed_peer,
                        step->replayed_peer, Reported(step->report)));
    Refresh();
    Progress(true);
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<StoredTrace>> open = store_->OpenSegment();
  if (!open.ok()) return open.status();
  if (open->empty()) return absl::OkStatus();

  // Replay, recall, learn and rewards (segment_step.h) on the segment.
  std::vector<size_t> indices;
  std::vector<core::MemoryTrace> segment;
  std::vector<v1::MemoryTrace> traces;
  for (StoredTrace& stored : *open) {
    indices.push_back(stored.source_index());
    segment.push_back(TraceFromProto(stored.trace()));
    traces.push_back(std::move(*stored.mutable_trace()));
  }
  absl::StatusOr<SegmentStepResult> step =
      StepSegment(std::move(segment), indices);
  if (!step.ok()) return step.status();
  for (size_t k = 0; k < traces.size(); ++k) {
    traces[k].set_reward_external(step->traces[k].reward_external);
    traces[k].set_reward(step->traces[k].reward);
  }
  const uint64_t dropped_before = store_->state().traces_dropped();
  absl::StatusOr<uint64_t> first_seq =
      store_->SealSegment(traces, [&](RobotState& state) {
        state.set_replayed_own(state.replayed_own() + step->replayed_own);
        state.set_replayed_peer(state.replayed_peer() + step->replayed_peer);
      });
  if (!first_seq.ok()) return first_seq.status();
  const RobotState state = store_->state();
  if (state.traces_dropped() > dropped_before) {
    Log(absl::StrFormat(
        "upload queue full (policy drop-oldest): dropped the %d oldest "
        "queued traces (%d dropped in all)",
        state.traces_dropped() - dropped_before, state.traces_dropped()));
  }
  for (size_t k = 0; k < traces.size(); ++k) {
    traces[k].set_seq(*first_seq + k);
    memory_.AddOwn(TraceFromProto(traces[k]));
  }
  Log(absl::StrFormat(
      "segment %d sealed: %d traces (seq %d..%d, mean R %.3f), replayed %d "
      "(%d of peers), recalled %d%s",
      state.segments(), traces.size(), *first_seq,
      *first_seq + traces.size() - 1,
      [&] {
        double sum = 0.0;
        for (const v1::MemoryTrace& trace : traces) sum += trace.reward();
        return sum / traces.size();
      }(),
      step->replayed_own + step->replayed_peer, step->replayed_peer,
      step->recalled, Reported(step->report)));
  SendRescored(step->rescored);
  Refresh();
  Progress(true);
  return absl::OkStatus();
}

void Agent::SendRescored(const std::vector<core::MemoryTrace>& rescored) {
  if (rescored.empty()) return;
  // Advisory, as a refresh is: one attempt; what the server did not take
  // is re-scored again after the next segment (still queued traces are
  // not held yet and go up with the R they were sealed with).
  absl::StatusOr<v1::UpdateRewardsResponse> updated =
      robot::SendRescored(*query_client_, options_.fleet_id, rescored, memory_);
  if (!updated.ok()) {
    Log(absl::StrCat("re-scoring ", rescored.size(),
                     " remembered traces: not taken (",
                     updated.status().ToString(), ")"));
    return;
  }
  absl::Status counted = store_->Update([&](RobotState& state) {
    state.set_traces_rescored(state.traces_rescored() + updated->updated());
  });
  if (!counted.ok()) Log(std::string(counted.message()));
  Log(absl::StrFormat(
      "re-scored %d remembered traces under the new head: %d updated, %d "
      "not held by the fleet",
      rescored.size(), updated->updated(), updated->not_held_size()));
}

void Agent::Refresh() {
  const uint32_t count =
      options_.refresh_count > 0
          ? options_.refresh_count
          : static_cast<uint32_t>(options_.dynamic_memory.capacity);
  absl::StatusOr<std::vector<v1::MemoryTrace>> sampled =
      query_client_->SampleReplay(options_.fleet_id, options_.robot_id, count);
  if (!sampled.ok()) {
    // A fleet nobody has uploaded to yet (the first robot) is no error.
    Log(absl::IsNotFound(sampled.status())
            ? std::string("refresh: the fleet holds no memory yet; the "
                          "dynamic memory keeps what it has")
            : absl::StrCat("refresh skipped (", sampled.status().ToString(),
                           "); the dynamic memory keeps what it has"));
    return;
  }
  std::vector<core::MemoryTrace> traces;
  uint64_t peers = 0;
  for (const v1::MemoryTrace& trace : *sampled) {
    traces.push_back(TraceFromProto(trace));
    peers += trace.robot_id() != options_.robot_id ? 1 : 0;
  }
  memory_.Refresh(traces);
  absl::Status updated = store_->Update([&](RobotState& state) {
    state.set_refreshes(state.refreshes() + 1);
    state.set_refreshed_peer_traces(state.refreshed_peer_traces() + peers);
  });
  if (!updated.ok()) SetFatal(updated);
}

void Agent::UploadLoop() {
  std::chrono::milliseconds backoff = options_.initial_backoff;
  bool unreachable = false;
  std::unique_ptr<client::Client> own_client;
  if (options_.new_upload_client) own_client = options_.new_upload_client();
  client::Client* uploader = own_client != nullptr ? own_client.get() : client_;
  int failures = 0;
  while (!stop_threads_.load()) {
    if (store_->queue().depth == 0) {  // in memory: no disk read when idle
      SleepUnless(std::chrono::milliseconds(50), stop_threads_);
      continue;
    }
    absl::StatusOr<std::vector<v1::MemoryTrace>> batch =
        store_->PeekQueue(std::max<size_t>(options_.upload_batch, 1));
    if (!batch.ok()) {
      SetFatal(batch.status());
      return;
    }
    if (batch->empty()) continue;  // dropped meanwhile (drop-oldest)
    absl::StatusOr<v1::UploadTracesResponse> response =
        uploader->Upload(options_.fleet_id, *batch);
    if (response.ok()) {
      failures = 0;
      absl::Status marked = store_->MarkUploaded(
          batch->back().seq(), response->accepted(), response->duplicates());
      if (!marked.ok()) {
        SetFatal(marked);
        return;
      }
      if (unreachable) {
        Log(absl::StrFormat("server reachable again; uploading (%d queued)",
                            store_->queue().depth));
        unreachable = false;
      }
      backoff = options_.initial_backoff;
      continue;
    }
    if (!IsRetryable(response.status().code())) {
      SetFatal(absl::Status(
          response.status().code(),
          absl::StrFormat("the server refused traces seq %d..%d: %s; every "
                          "queued trace stays in the queue (%d)",
                          batch->front().seq(), batch->back().seq(),
                          response.status().message(), store_->queue().depth)));
      Log(std::string(fatal().message()));
      return;
    }
    {
      absl::MutexLock lock(&mu_);
      last_error_ = response.status().ToString();
    }
    if (!unreachable) {
      Log(absl::StrFormat(
          "cannot upload (%s); %d traces stay queued, retrying with backoff",
          response.status().ToString(), store_->queue().depth));
      unreachable = true;
    }
    if (own_client != nullptr && options_.reconnect_after_failures > 0 &&
        ++failures >= options_.reconnect_after_failures) {
      // A fresh channel (and subchannel): what a restart of the robot
      // would give it.
      own_client = options_.new_upload_client();
      uploader = own_client.get();
      failures = 0;
      Log("uploader: opened a new connection to the server");
    }
    SleepUnless(backoff, stop_threads_);
    backoff = std::min(backoff * 2, options_.max_backoff);
  }
}

void Agent::WatchLoop() {
  while (!stop_threads_.load()) {
    const uint64_t cursor = store_->state().watch_cursor();
    absl::StatusOr<uint64_t> last = client_->Watch(
        options_.fleet_id, cursor,
        [this](const v1::MemoryEvent& event) {
          absl::Status updated = store_->Update([&](RobotState& state) {
            state.set_watch_cursor(event.id());
            state.set_events_seen(state.events_seen() + 1);
            if (event.type() == v1::MemoryEvent::CLUSTER_ADDED &&
                event.robot_id() != options_.robot_id) {
              state.set_peer_clusters_added(state.peer_clusters_added() + 1);
            } else if (event.type() == v1::MemoryEvent::CLUSTER_FORGOTTEN ||
                       event.type() == v1::MemoryEvent::CLUSTER_MERGED) {
              state.set_clusters_forgotten(state.clusters_forgotten() + 1);
            }
          });
          if (!updated.ok()) SetFatal(updated);
          return updated.ok();
        },
        &stop_threads_, std::chrono::milliseconds(200));
    if (stop_threads_.load()) return;
    // The fleet may not exist yet, or the server is away: look again soon.
    if (!last.ok() && !watch_error_logged_) {
      Log(absl::StrCat("watch: ", last.status().ToString(), "; retrying"));
      watch_error_logged_ = true;
    }
    SleepUnless(std::chrono::seconds(1), stop_threads_);
  }
}

void Agent::WriteStatus(std::string_view phase, bool force) {
  if (options_.status_file.empty()) return;
  const auto now = Clock::now();
  if (!force && now - last_status_ < options_.status_interval) return;
  last_status_ = now;
  RobotStatus status;
  status.set_robot_id(options_.robot_id);
  status.set_fleet_id(options_.fleet_id);
  status.set_source(source_->description());
  status.set_encoder_version(encoder_->version());
  status.set_phase(std::string(phase));
  status.set_source_size(source_->size());
  status.set_source_end(end_);
  *status.mutable_counters() = store_->state();
  const QueueInfo queue = store_->queue();
  status.set_queue_depth(queue.depth);
  status.set_queue_bytes(queue.bytes);
  status.set_queue_max_bytes(store_->options().max_bytes);
  const int64_t now_ns = absl::ToUnixNanos(absl::Now());
  status.set_queue_oldest_age_s(queue.oldest_stored_unix_ns == 0
                                    ? 0.0
                                    : (now_ns - queue.oldest_stored_unix_ns) /
                                          1e9);
  status.set_open_segment(queue.open_segment);
  status.set_dynamic_memory_size(memory_.size());
  for (const auto& [robot, count] : memory_.CountByRobot()) {
    (*status.mutable_dynamic_memory_by_robot())[robot] = count;
  }
  const core::FirstCorrectRanks ranks = RelocalisationRanks(status.counters());
  status.set_relocalisation_scored(ranks.size());
  status.set_relocalisation_recall_at_1(core::RecallAtK(ranks, 1));
  status.set_relocalisation_recall_at_5(core::RecallAtK(ranks, 5));
  status.set_relocalisation_weighted_recall(core::WeightedRecall(ranks));
  const core::FirstCorrectRanks sequence = SequenceRanks(status.counters());
  status.set_sequence_recall_at_1(core::RecallAtK(sequence, 1));
  status.set_sequence_recall_at_5(core::RecallAtK(sequence, 5));
  status.set_sequence_weighted_recall(core::WeightedRecall(sequence));
  const uint64_t answered =
      ranks.size() + status.counters().relocalisation_unscored();
  status.set_relocalisation_ms_mean(
      answered == 0 ? 0.0
                    : status.counters().relocalisation_ms_total() / answered);
  {
    absl::MutexLock lock(&mu_);
    status.set_last_error(last_error_);
  }
  status.set_updated_unix_ns(now_ns);
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.add_whitespace = true;
  print.always_print_primitive_fields = true;
  // The canonical JSON mapping (lowerCamelCase), as the REST API and
  // `fleetmem --json` write it.
  if (!google::protobuf::util::MessageToJsonString(status, &json, print).ok()) {
    return;
  }
  // Write-then-rename, so that a reader never sees half a file.
  const std::string tmp = options_.status_file + ".tmp";
  std::error_code error;
  {
    std::ofstream out(tmp, std::ios::trunc);
    out << json;
    out.close();
    if (!out) error = std::make_error_code(std::errc::io_error);
  }
  if (!error) std::filesystem::rename(tmp, options_.status_file, error);
  if (error && !status_write_failed_) {
    Log(absl::StrCat("cannot write the status file ", options_.status_file,
                     ": ", error.message(), " (the robot goes on)"));
  }
  status_write_failed_ = static_cast<bool>(error);
}

void Agent::Progress(bool force) {
  const auto now = Clock::now();
  if (!force && now - last_progress_ < options_.progress_interval) return;
  last_progress_ = now;
  const RobotState state = store_->state();
  const QueueInfo queue = store_->queue();
  const core::FirstCorrectRanks ranks = RelocalisationRanks(state);
  const core::FirstCorrectRanks sequence = SequenceRanks(state);
  const double age =
      queue.oldest_stored_unix_ns == 0
          ? 0.0
          : (absl::ToUnixNanos(absl::Now()) - queue.oldest_stored_unix_ns) /
                1e9;
  Log(absl::StrFormat(
      "%s: observed %d/%d | queue %d (oldest %.1f s) | uploaded %d | "
      "refreshed %d (M_D %d, %d traces from peers) | replayed %d from "
      "peers | relocalisation %s%s%s%s",
      phase_, state.next_index(), end_, queue.depth, age,
      state.traces_uploaded(), state.refreshes(), memory_.size(),
      state.refreshed_peer_traces(), state.replayed_peer(),
      // Nothing scored yet (no query, or none with ground truth): no rate.
      ranks.empty() ? std::string("not scored yet")
                    : absl::StrFormat("r@1 %.3f over %d",
                                      core::RecallAtK(ranks, 1), ranks.size()),
      sequence.empty() ? std::string()
                       : absl::StrFormat(", over sequences of %d r@1 %.3f",
                                         options_.sequence.length,
                                         core::RecallAtK(sequence, 1)),
      state.relocalisation_unscored() == 0
          ? std::string()
          : absl::StrFormat(" (%d more without ground truth)",
                            state.relocalisation_unscored()),
      OwnOnlyNote(state.relocalisation_own_only(), ranks.size())));
}

}  // namespace fleetmem::robot
