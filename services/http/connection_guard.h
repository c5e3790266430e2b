// What one client may hold of the HTTP port.
//
// cpp-httplib 0.11 (Debian's) serves a connection on one thread of a fixed
// pool for as long as the client keeps it open, bounds a request only per
// read (a client sending a byte every few seconds is never timed out) and
// takes any number of connections: eight slow clients held all eight threads
// and the readiness probe went unanswered. The guard is the server's task
// queue instead of httplib's pool:
//   - every connection gets a thread of its own, up to max_connections;
//   - a client (an IP address) holds at most max_connections_per_client;
//   - a connection whose request head (request line and headers; the TLS
//     handshake too) has not arrived within head_timeout of its start or of
//     the previous answer, or whose body has not within body_timeout, is
//     closed; a handler (a watch) has no deadline of its own;
//   - a connection that has sent more than max_head_bytes for one request
//     head is closed (httplib 0.11 bounds a header line, not their count).
// Connections over a limit are answered 503 and closed at once.
//
// httplib hides a connection's socket from its task queue, so the guard
// learns it where httplib gets it: this library interposes the C library's
// accept(), which records the socket accepted last on the calling thread
// (httplib accepts and enqueues on its listening thread).
#ifndef FLEETMEM_SERVICES_HTTP_CONNECTION_GUARD_H_
#define FLEETMEM_SERVICES_HTTP_CONNECTION_GUARD_H_

#include <condition_variable>
#include <cstddef>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/time/time.h"
#include "httplib.h"
#include "services/http/connection_limits.h"

namespace fleetmem::http {

class ConnectionGuard final : public httplib::TaskQueue {
 public:
  explicit ConnectionGuard(ConnectionLimits limits);
  ~ConnectionGuard() override;

  // On httplib's listening thread, right after accept(): `fn` serves the
  // connection accepted last and closes its socket.
  void enqueue(std::function<void()> fn) override;
  // Ends the deadline checks and waits for every connection's thread.
  void shutdown() override;

  // Phase marks, called on the connection's thread (no-ops elsewhere):
  // the head arrived (httplib's pre-routing handler), a handler runs, an
  // answer was sent (httplib's logger: the connection waits for the next
  // request).
  static void HeadRead();
  static void Handling();
  static void AnswerSent();
  // On the connection's thread: true once the client has closed the
  // connection (or reset it); false elsewhere. A watch asks this between
  // its events, so that a closed watcher gives back its slot at once
  // instead of at the next write.
  static bool PeerClosed();
  // On the connection's thread: the connection is shut once the answer
  // being made is sent (httplib closes a connection only when the request
  // asks to).
  static void CloseAfterAnswer();

 private:
  enum class Phase { kHead, kBody, kHandling, kClosed };
  struct Connection {
    ConnectionGuard* guard = nullptr;
    int socket = -1;  // our duplicate: shutdown() never hits a reused fd
    std::string client;
    Phase phase = Phase::kHead;
    absl::Time since;
    // Bytes read from the socket when the phase began (0 where the kernel
    // does not say).
    uint64_t read_at_phase = 0;
    bool close_after_answer = false;
  };

  // A connection over a limit, waiting in the overflow loop for its
  // request line (ConnectionLimits::probe).
  struct Overflow {
    int socket = -1;  // our duplicate
    std::function<void()> fn;
    std::string refused;  // why it is over a limit
    std::string head;
    absl::Time deadline;
  };
  void Serve(std::shared_ptr<Connection> connection, std::function<void()> fn);
  void OverflowLoop();
  // Answers (a probe) or refuses the connection, then lets httplib close it.
  void Finish(Overflow& overflow);
  void Worker();
  void CheckDeadlines();
  static void Mark(Phase phase);

  const ConnectionLimits limits_;
  std::mutex mu_;
  std::condition_variable wake_;
  bool stopping_ = false;
  std::deque<std::function<void()>> tasks_;
  size_t idle_workers_ = 0;
  std::vector<std::thread> workers_;
  std::vector<std::shared_ptr<Connection>> open_;
  std::map<std::string, size_t> per_client_;
  std::thread deadlines_;
  // Connections over a limit handed to the overflow loop (guarded by mu_).
  std::vector<Overflow> incoming_;
  std::condition_variable overflow_wake_;
  std::thread overflow_;
};

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_CONNECTION_GUARD_H_
