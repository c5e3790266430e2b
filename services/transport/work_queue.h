// A small bounded pool of worker threads for the engine's blocking calls
// (they fsync), so that gRPC's callback threads never block on storage.
#ifndef FLEETMEM_SERVICES_TRANSPORT_WORK_QUEUE_H_
#define FLEETMEM_SERVICES_TRANSPORT_WORK_QUEUE_H_

#include <cstddef>
#include <deque>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/functional/any_invocable.h"
#include "absl/synchronization/mutex.h"

namespace fleetmem::transport {

struct WorkQueueOptions {
  // Worker threads; 0 means 2 x std::thread::hardware_concurrency() (at
  // least 2).
  size_t threads = 0;
  // Tasks that may wait for a free worker; TrySubmit refuses more (the
  // transport then answers RESOURCE_EXHAUSTED).
  size_t max_queued = 1024;
};

// Thread-safe. Every task that TrySubmit accepts runs exactly once, on one of
// the workers, even if Stop is called before it started.
class WorkQueue {
 public:
  // Starts the workers.
  explicit WorkQueue(WorkQueueOptions options = {});
  // Stop().
  ~WorkQueue();
  WorkQueue(const WorkQueue&) = delete;
  WorkQueue& operator=(const WorkQueue&) = delete;

  // Queues `task`; false (and `task` is dropped unrun) if max_queued tasks
  // are already waiting or Stop has been called.
  bool TrySubmit(absl::AnyInvocable<void() &&> task);

  // Refuses new tasks, runs the queued ones, joins the workers. Idempotent;
  // must not be called from a task.
  void Stop();

  size_t threads() const { return workers_.size(); }
  // Tasks waiting for a worker now (for logs and tests).
  size_t queued() const;

 private:
  void Work();

  const size_t max_queued_;
  mutable absl::Mutex mu_;
  std::deque<absl::AnyInvocable<void() &&>> tasks_ ABSL_GUARDED_BY(mu_);
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::vector<std::thread> workers_;
};

// The number of workers `options` asks for (threads, or the default).
size_t WorkerThreads(const WorkQueueOptions& options);

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_WORK_QUEUE_H_
