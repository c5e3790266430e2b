// The robot's lifelong loop (BioSLAM Algorithm 3, memory.md), over one
// observation source, against one fleet:
//
//   for each observation q (from where the robot stopped last time):
//     encode z = E(q); R_in = 1 - cos(E(q), E(A(q)))        (Eq. 12)
//     relocalise: QueryPlace(z) against the whole fleet, scored against the
//       observation's known place
//     record (z, p, R_in) durably with the source position  (robot_store.h)
//   at the end of each segment (200 observations by default, and at the
//   end of the source), the step fleetmem-eval measures (segment_step.h):
//     replay: draw from the dynamic memory M_D                (Eq. 19)
//     recall: the fleet's traces of each new observation's place
//     learner: train on the segment, the replayed and remembered traces
//     R_ex under the learner (or the triplet loss in code space);
//       R = R_ex + R_in                                      (Eqs. 11, 13)
//   then:
//     seal the segment into the upload queue (seqs given here, durably)
//     add the robot's own traces to M_D; refresh M_D from the fleet
//       (SampleReplay, Eq. 18)
//
// Beside the loop, an uploader thread drains the queue in order, in batches,
// whenever the server answers (store-and-forward), and a watcher thread
// follows WatchMemory from its durable cursor. Upload errors that a retry
// can mend (UNAVAILABLE, DEADLINE_EXCEEDED, RESOURCE_EXHAUSTED, ABORTED) are
// retried with backoff for as long as it takes; any other is fatal: the
// robot stops observing and Run returns it, and the queue keeps every trace.
#ifndef FLEETMEM_CLIENTS_ROBOT_RUNTIME_AGENT_H_
#define FLEETMEM_CLIENTS_ROBOT_RUNTIME_AGENT_H_

#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <random>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/memory/dynamic_memory.h"
#include "clients/robot/memory/robot_store.h"
#include "clients/robot/runtime/segment_step.h"
#include "clients/robot/sensing/encoder.h"
#include "clients/robot/sensing/observation_hook.h"
#include "clients/robot/sensing/observation_source.h"
#include "clients/robot/sensing/rewards.h"
#include "clients/robot/sensing/sequence_search.h"

namespace fleetmem::robot {

// True for the server errors a robot waits out and retries (UNAVAILABLE,
// DEADLINE_EXCEEDED, RESOURCE_EXHAUSTED, ABORTED); any other error is an
// answer.
bool IsRetryable(absl::StatusCode code);

// R_in of an observation whose code is `code` (Eq. 12): 1 - cos of the
// code and the code of a perturbed copy, the perturbation's generator
// seeded by `seed` and the source index, so that a repeated observation
// (after a crash, or re-encoded by a migration) gets the same draw.
absl::StatusOr<float> InternalRewardOf(const Encoder& encoder,
                                       const Observation& observation,
                                       std::span<const float> code,
                                       uint64_t seed, size_t index);

struct AgentOptions {
  std::string fleet_id;
  std::string robot_id;
  // Domain of the traces ("summer", "lidar").
  std::string domain;
  // Observations per segment (the paper's ~200, about 2 km).
  size_t segment_size = 200;
  // Observe source indices [first, last); last is clamped to the source.
  size_t first = 0;
  size_t last = std::numeric_limits<size_t>::max();
  // Observations per second (0 = as fast as possible): emulates a sensor.
  double rate_hz = 0.0;
  // Upload traces (a query-only robot relocalises and uploads nothing).
  bool upload = true;
  // Relocalise every observation against the fleet (k matches).
  bool relocalise = true;
  uint32_t query_k = 6;
  // A match within this distance of the true place is correct (place units).
  double match_radius = 20.0;
  // Relocalise over the last `sequence.length` frames as well
  // (sequence_search.h; its tolerance is match_radius): each answer is
  // re-ranked by the sequence and scored apart (sequence_ranks). 1 = single
  // frames only. The server is then asked for sequence_candidates matches
  // (at least query_k); the single-frame score takes the first query_k.
  // The distance travelled between frames is taken from the observations'
  // places (the robot's odometry; on Nordland and KITTI, their ground truth).
  SequenceSearchOptions sequence{.length = 1};
  uint32_t sequence_candidates = 20;
  // Score relocalisations (only where the source's places are ground truth;
  // a laser log's are odometry).
  bool score_relocalisation = true;
  // The end-of-segment step (segment_step.h): replay draws, place recall
  // through `query_client` (QueryPlace within match_radius of each new
  // observation's place: the traces a learner pairs it with), rewards.
  SegmentStepOptions step;
  DynamicMemoryOptions dynamic_memory;
  // Traces asked of the fleet per refresh (Eq. 18); 0 = the capacity of M_D.
  uint32_t refresh_count = 0;
  // A new robot with a learner (nothing observed yet) fits it on its first
  // refresh before its first observation when that brought two domains or
  // more (WarmStart in segment_step.h).
  bool warm_start = true;
  // Traces per upload call.
  size_t upload_batch = 200;
  // Backoff of the uploader while the server cannot take traces.
  std::chrono::milliseconds initial_backoff{200};
  std::chrono::milliseconds max_backoff{5000};
  // The uploader's own client, made by this factory (null: it uploads
  // through `client`). After `reconnect_after_failures` failed uploads in a
  // row it is replaced by a new one: a TLS channel of gRPC 1.51 may never
  // reconnect after a network outage until it is reopened (grpc/grpc#33593;
  // docs/deployment.md). 0 never replaces it.
  std::function<std::unique_ptr<client::Client>()> new_upload_client;
  int reconnect_after_failures = 6;
  // At the end of the source: how long to wait for the queue to drain.
  std::chrono::milliseconds drain_timeout{120000};
  // Status file (JSON) rewritten at least this often; empty path = none.
  std::string status_file;
  std::chrono::milliseconds status_interval{1000};
  // Progress lines at least this often (and at every segment).
  std::chrono::milliseconds progress_interval{5000};
  // Seed of R_in's perturbations and of replay draws.
  uint64_t seed = 1;
  // Where progress and log lines go (default: stderr).
  std::function<void(std::string_view)> log;
};

// What Run did, for the summary line.
struct AgentSummary {
  RobotState state;
  QueueInfo queue;
  // Observations this run made (not counting earlier runs).
  uint64_t observed_this_run = 0;
  bool source_finished = false;
  bool drained = false;
};

class Agent {
 public:
  // `client` uploads, samples and watches; `query_client` relocalises and
  // refreshes (one attempt per call with a short deadline, so that an
  // unreachable server does not hold the loop). Neither may be null; they
  // may be the same. `learner` and `hook` may be null.
  Agent(AgentOptions options, client::Client* client,
        client::Client* query_client, const ObservationSource* source,
        const Encoder* encoder, RobotStore* store, Learner* learner = nullptr,
        ObservationHook* hook = nullptr);
  ~Agent();

  // Runs until the source ends (then drains the queue, bounded by
  // drain_timeout) or `stop` becomes true (then returns at once: everything
  // observed is uploaded or durable). Returns the first fatal error (a bad
  // observation, a refused upload, a failing disk) with what was kept.
  absl::Status Run(const std::atomic<bool>& stop);

  AgentSummary summary() const;

 private:
  // Run's steps: the source position to start at (where the last run
  // stopped, or options.first), written to the store; a sleep that keeps
  // rate_hz; the queue's drain once the source is done (drain_timeout).
  absl::StatusOr<size_t> StartPosition();
  void Pace(std::chrono::steady_clock::time_point run_start,
            const std::atomic<bool>& stop);
  void Drain(const std::atomic<bool>& stop);
  absl::Status ObserveOne(size_t index, const std::atomic<bool>& stop);
  // One QueryPlace for an observation and how it scored.
  struct Relocalisation {
    int rank = -1;  // first correct rank (0: none in the top k); -1 unscored
    int sequence_rank = -1;   // the same, re-ranked by the sequence
    bool unanswered = false;  // the server did not answer
    bool empty = false;       // the fleet's memory is empty (or absent)
    bool unscored = false;    // answered, but the place is not ground truth
    bool own_only = false;    // every answer one of this robot's traces
    double ms = 0.0;
    // Adds this query to the durable counters.
    void CountIn(RobotState& state) const;
  };
  Relocalisation Relocalise(const std::vector<float>& code,
                            const core::Place& place);
  // ObserveOne's ends: a query-only robot's observation (its position and
  // scores, and its code for the segment's recall); an uploading robot's
  // trace recorded in its queue, waiting while the queue is full (policy
  // refuse) until it has room or `stop`.
  absl::Status RecordQuery(size_t index, const Observation& observation,
                           std::vector<float> code,
                           const Relocalisation& relocalisation);
  absl::Status Record(size_t index, const v1::MemoryTrace& trace,
                      const Relocalisation& relocalisation,
                      const std::atomic<bool>& stop);
  // Ends a segment: replay, learner, rewards, seal (uploading robot), then
  // refresh.
  absl::Status SealSegment();
  // The segment step (segment_step.h) over `segment`, observed at source
  // `indices`.
  absl::StatusOr<SegmentStepResult> StepSegment(
      std::vector<core::MemoryTrace> segment,
      const std::vector<size_t>& indices);
  // Sends the step's re-scored remembered traces (UpdateRewards) and gives
  // M_D their new R; logged, never fatal.
  void SendRescored(const std::vector<core::MemoryTrace>& rescored);
  void Refresh();
  void UploadLoop();
  void WatchLoop();
  void WriteStatus(std::string_view phase, bool force);
  void Progress(bool force);
  void Log(const std::string& line) const;
  absl::Status fatal() const;
  void SetFatal(absl::Status status);
  // Sleeps up to `duration`, returning early once `stop` is set.
  static void SleepUnless(std::chrono::milliseconds duration,
                          const std::atomic<bool>& stop);

  const AgentOptions options_;
  client::Client* const client_;
  client::Client* const query_client_;
  const ObservationSource* const source_;
  const Encoder* const encoder_;
  RobotStore* const store_;
  Learner* const learner_;
  ObservationHook* const hook_;
  DynamicMemory memory_;
  std::mt19937_64 rng_;
  size_t end_ = 0;
  // Source indices of a query-only robot's open segment (not durable: only
  // replay depends on it).
  // A query-only robot's open segment: source indices and their traces.
  std::vector<size_t> query_indices_;
  std::vector<core::MemoryTrace> query_segment_;
  // The last frames' answers, for the sequence search (main thread).
  SequenceWindow window_;
  uint64_t observed_this_run_ = 0;
  bool source_finished_ = false;
  bool drained_ = false;
  std::string phase_ = "starting";
  // One log line per kind of trouble, not one per attempt.
  bool status_write_failed_ = false;  // main thread
  bool watch_error_logged_ = false;   // watcher thread

  std::atomic<bool> stop_threads_{false};
  mutable absl::Mutex mu_;
  absl::Status fatal_ ABSL_GUARDED_BY(mu_);
  std::string last_error_ ABSL_GUARDED_BY(mu_);
  std::chrono::steady_clock::time_point last_status_{};
  std::chrono::steady_clock::time_point last_progress_{};
};

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_RUNTIME_AGENT_H_
