// Load for fleetmem-server: robots that upload deterministic traces over the
// client library, an acknowledgement log of every batch the server accepted,
// its verification after a crash, and samples of a server process's RSS and
// file descriptors. Used by fleetmem-load (crash trials, soak, peak).
#ifndef FLEETMEM_TOOLS_LOAD_LOAD_GENERATOR_H_
#define FLEETMEM_TOOLS_LOAD_LOAD_GENERATOR_H_

#include <atomic>
#include <chrono>
#include <cstdint>
#include <map>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "clients/cpp/fleetmem_client.h"
#include "fleetmem/v1/memory.pb.h"

namespace fleetmem::load {

// Trace `seq` of `robot_id`: a pure function of its arguments (so a batch
// can be re-sent after a crash to check it is stored).
v1::MemoryTrace LoadTrace(const std::string& robot_id, uint64_t seq,
                          int dimension);

struct UploadLoadOptions {
  std::string fleet_id = "load";
  // Robots load-0 .. load-(N-1), one thread and one stream per upload each.
  int robots = 4;
  // Traces per UploadTraces call.
  int batch = 50;
  int dimension = 128;
  // Traces per second over all robots; 0 uploads as fast as possible.
  double rate = 0;
  // Stop after this long (or when stop is set).
  std::chrono::milliseconds duration{10000};
  // First seq of every robot (a later run continues after an earlier one).
  uint64_t first_seq = 1;
  // Stop a robot at its first failed call (crash trials) instead of
  // retrying the batch.
  bool stop_on_error = false;
  // > 0: codes, rewards and places repeat with period code_pool per robot
  // (generated once), so that making traces costs the client little next to
  // sending them (benchmarks); 0: every trace is LoadTrace(robot, seq).
  int code_pool = 0;
  // > 0: stop once this many traces (all robots) were acknowledged.
  uint64_t max_traces = 0;
};

// Latencies of calls, in milliseconds.
class LatencyLog {
 public:
  void Add(double ms);
  // {p50, p90, p99, p99.9, max, count} of what was added since the last
  // Take(), from every latency kept (exact order statistics; Debian has no
  // C/C++ HdrHistogram, whose buckets approximate these).
  struct Summary {
    double p50 = 0, p90 = 0, p99 = 0, p999 = 0, max = 0;
    size_t count = 0;
  };
  Summary Take();

 private:
  std::mutex mu_;
  std::vector<double> ms_;
};

struct UploadLoadResult {
  uint64_t acknowledged = 0;  // traces in batches answered OK
  uint64_t failed_calls = 0;
  double seconds = 0;
  // Per robot: the next seq it would have sent.
  std::vector<uint64_t> next_seq;
  std::string first_error;
};

// Runs the robots. Every batch answered OK is appended to `ack_log` (if not
// empty) as "ROBOT FIRST LAST" and flushed before the next batch is sent;
// every call's latency goes to `latencies` (if not null).
absl::StatusOr<UploadLoadResult> RunUploads(const client::ClientOptions& client,
                                            const UploadLoadOptions& options,
                                            const std::string& ack_log,
                                            const std::atomic<bool>* stop,
                                            LatencyLog* latencies);

struct VerifyResult {
  uint64_t acknowledged = 0;  // traces in the log
  uint64_t present = 0;       // of them, reported as duplicates on re-send
  uint64_t lost = 0;          // of them, accepted as new: they were lost
};

// Re-sends every batch of `ack_log`: a stored trace comes back as a
// duplicate, a lost one is accepted (and counted in `lost`).
absl::StatusOr<VerifyResult> VerifyAcknowledged(
    const client::ClientOptions& client, const std::string& fleet_id,
    int dimension, const std::string& ack_log);

// Resident set size (bytes) and open file descriptors of process `pid`.
struct ProcessSample {
  uint64_t rss_bytes = 0;
  int open_fds = 0;
};
absl::StatusOr<ProcessSample> SampleProcess(int pid);

// Every sample of http://HTTP_ADDRESS/metrics (the Prometheus text format),
// keyed by the series as it is written there: a name and its labels, e.g.
// `fleetmem_heap_bytes{kind="free"}`. UNAVAILABLE if the server does not
// answer 200.
absl::StatusOr<std::map<std::string, double>> ScrapeMetrics(
    const std::string& http_address);

}  // namespace fleetmem::load

#endif  // FLEETMEM_TOOLS_LOAD_LOAD_GENERATOR_H_
