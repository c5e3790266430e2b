#include "services/http/connection_guard.h"

#include <arpa/inet.h>
#include <dlfcn.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <string_view>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/time/clock.h"
#include "services/http/socket_bytes.h"

namespace {

// The socket accept() returned last on this thread.
thread_local int last_accepted = -1;

}  // namespace

// Interposes the C library's accept() for the whole process (see the
// header): the same call, and the socket is remembered for the guard.
extern "C" int accept(int socket, struct sockaddr* address, socklen_t* length) {
  using Accept = int (*)(int, struct sockaddr*, socklen_t*);
  static const Accept next =
      reinterpret_cast<Accept>(dlsym(RTLD_NEXT, "accept"));
  const int accepted = next(socket, address, length);
  last_accepted = accepted;
  return accepted;
}

namespace fleetmem::http {
namespace {

// The connection the calling thread serves, if it is a guard's.
thread_local void* current = nullptr;

// Connections over a limit that the overflow loop holds at most (more are
// refused at once), and the bytes of a request line it reads.
constexpr size_t kMaxOverflow = 1024;
constexpr size_t kMaxOverflowHead = 2048;

std::string PeerAddress(int socket) {
  sockaddr_storage address{};
  socklen_t length = sizeof(address);
  if (getpeername(socket, reinterpret_cast<sockaddr*>(&address), &length) !=
      0) {
    return "unknown";
  }
  char text[INET6_ADDRSTRLEN] = {0};
  if (address.ss_family == AF_INET) {
    inet_ntop(AF_INET, &reinterpret_cast<sockaddr_in*>(&address)->sin_addr,
              text, sizeof(text));
  } else if (address.ss_family == AF_INET6) {
    inet_ntop(AF_INET6, &reinterpret_cast<sockaddr_in6*>(&address)->sin6_addr,
              text, sizeof(text));
  } else {
    return "local";
  }
  return text;
}

// A short answer for a connection refused before httplib reads it (plain
// HTTP; a TLS client sees a failed handshake).
void Refuse(int socket, const std::string& why) {
  const std::string body = absl::StrCat(
      "{\"code\":8,\"status\":\"RESOURCE_EXHAUSTED\",\"message\":\"", why,
      "\"}");
  const std::string answer = absl::StrCat(
      "HTTP/1.1 503 Service Unavailable\r\nConnection: close\r\n"
      "Content-Type: application/json\r\nRetry-After: 1\r\n"
      "Content-Length: ",
      body.size(), "\r\n\r\n", body);
  (void)send(socket, answer.data(), answer.size(), MSG_DONTWAIT | MSG_NOSIGNAL);
  shutdown(socket, SHUT_RDWR);
}

}  // namespace

ConnectionGuard::ConnectionGuard(ConnectionLimits limits)
    : limits_(std::move(limits)) {
  deadlines_ = std::thread([this] {
    std::unique_lock<std::mutex> lock(mu_);
    while (!stopping_) {
      wake_.wait_for(lock, absl::ToChronoMilliseconds(limits_.check_every));
      if (!stopping_) {
        lock.unlock();
        CheckDeadlines();
        lock.lock();
      }
    }
  });
}

ConnectionGuard::~ConnectionGuard() { shutdown(); }

void ConnectionGuard::enqueue(std::function<void()> fn) {
  const int socket = std::exchange(last_accepted, -1);
  auto connection = std::make_shared<Connection>();
  connection->guard = this;
  connection->since = absl::Now();
  std::string refused;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (socket >= 0) {
      connection->client = PeerAddress(socket);
      if (open_.size() >= limits_.max_connections) {
        refused = absl::StrCat("the server holds max_connections (",
                               limits_.max_connections, ") connections");
      } else if (per_client_[connection->client] >=
                 limits_.max_connections_per_client) {
        refused = absl::StrCat(
            connection->client, " holds max_connections_per_client (",
            limits_.max_connections_per_client, ") connections");
      } else {
        connection->socket = dup(socket);
        ++per_client_[connection->client];
        open_.push_back(connection);
      }
    }
  }
  if (!refused.empty()) {
    if (limits_.probe && socket >= 0) {
      std::lock_guard<std::mutex> lock(mu_);
      if (!stopping_ && incoming_.size() < kMaxOverflow) {
        incoming_.push_back({dup(socket), std::move(fn), std::move(refused),
                             std::string(), absl::Now() + limits_.probe_wait});
        if (!overflow_.joinable()) {
          overflow_ = std::thread([this] { OverflowLoop(); });
        }
        overflow_wake_.notify_one();
        return;
      }
    }
    if (limits_.on_refused) limits_.on_refused(refused);
    Refuse(socket, refused);
    fn();  // reads nothing from the shut socket, and closes it
    return;
  }
  std::lock_guard<std::mutex> lock(mu_);
  tasks_.push_back([this, connection, fn = std::move(fn)]() mutable {
    Serve(std::move(connection), std::move(fn));
  });
  // A thread for every connection waiting (idle threads are counted until
  // they take a task).
  if (tasks_.size() > idle_workers_) {
    workers_.emplace_back([this] { Worker(); });
  } else {
    wake_.notify_all();
  }
}

void ConnectionGuard::OverflowLoop() {
  std::vector<Overflow> pending;
  while (true) {
    {
      std::unique_lock<std::mutex> lock(mu_);
      if (pending.empty()) {
        overflow_wake_.wait(lock,
                            [this] { return stopping_ || !incoming_.empty(); });
      }
      for (Overflow& overflow : incoming_)
        pending.push_back(std::move(overflow));
      incoming_.clear();
      if (stopping_) {
        lock.unlock();
        for (Overflow& overflow : pending) Finish(overflow);
        return;
      }
    }
    std::vector<pollfd> wait;
    for (const Overflow& overflow : pending) {
      wait.push_back({overflow.socket, POLLIN, 0});
    }
    ::poll(wait.data(), wait.size(), 10);
    const absl::Time now = absl::Now();
    std::vector<Overflow> still;
    for (size_t i = 0; i < pending.size(); ++i) {
      Overflow& overflow = pending[i];
      bool done = now >= overflow.deadline;
      if (wait[i].revents != 0) {
        char buffer[1024];
        const ssize_t n =
            recv(overflow.socket, buffer, sizeof(buffer), MSG_DONTWAIT);
        if (n > 0) overflow.head.append(buffer, static_cast<size_t>(n));
        done = done || n == 0 ||
               (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK) ||
               overflow.head.find("\r\n") != std::string::npos ||
               overflow.head.size() >= kMaxOverflowHead;
      }
      if (done) {
        Finish(overflow);
      } else {
        still.push_back(std::move(overflow));
      }
    }
    pending = std::move(still);
  }
}

void ConnectionGuard::Finish(Overflow& overflow) {
  // "GET /readyz HTTP/1.1": a probe is answered, anything else refused.
  std::optional<std::pair<int, std::string>> answer;
  const size_t line_end = overflow.head.find("\r\n");
  if (line_end != std::string::npos) {
    const std::vector<absl::string_view> words = absl::StrSplit(
        absl::string_view(overflow.head).substr(0, line_end), ' ');
    if (words.size() == 3 && (words[0] == "GET" || words[0] == "HEAD")) {
      const absl::string_view path = words[1].substr(0, words[1].find('?'));
      answer = limits_.probe(std::string_view(path.data(), path.size()));
    }
  }
  if (answer.has_value()) {
    const std::string response = absl::StrCat(
        "HTTP/1.1 ", answer->first, answer->first == 200 ? " OK" : " Error",
        "\r\nConnection: close\r\nContent-Type: text/plain\r\n"
        "Content-Length: ",
        answer->second.size(), "\r\n\r\n", answer->second);
    (void)send(overflow.socket, response.data(), response.size(),
               MSG_DONTWAIT | MSG_NOSIGNAL);
    ::shutdown(overflow.socket, SHUT_RDWR);
  } else {
    if (limits_.on_refused) limits_.on_refused(overflow.refused);
    Refuse(overflow.socket, overflow.refused);
  }
  close(overflow.socket);
  overflow.fn();  // reads nothing from the shut socket, and closes it
}

void ConnectionGuard::Serve(std::shared_ptr<Connection> connection,
                            std::function<void()> fn) {
  current = connection->socket >= 0 ? connection.get() : nullptr;
  fn();
  current = nullptr;
  std::lock_guard<std::mutex> lock(mu_);
  if (connection->socket < 0) return;
  close(connection->socket);
  if (--per_client_[connection->client] == 0) {
    per_client_.erase(connection->client);
  }
  open_.erase(std::find(open_.begin(), open_.end(), connection));
}

void ConnectionGuard::Worker() {
  std::unique_lock<std::mutex> lock(mu_);
  while (true) {
    ++idle_workers_;
    wake_.wait(lock, [this] { return stopping_ || !tasks_.empty(); });
    --idle_workers_;
    if (tasks_.empty()) return;  // stopping, nothing left
    std::function<void()> task = std::move(tasks_.front());
    tasks_.pop_front();
    lock.unlock();
    task();
    lock.lock();
  }
}

void ConnectionGuard::CheckDeadlines() {
  const absl::Time now = absl::Now();
  std::vector<std::string> closed;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const std::shared_ptr<Connection>& connection : open_) {
      const absl::Duration waited = now - connection->since;
      const bool late =
          (connection->phase == Phase::kHead &&
           waited > limits_.head_timeout) ||
          (connection->phase == Phase::kBody && waited > limits_.body_timeout);
      uint64_t head_bytes = 0;
      if (connection->phase == Phase::kHead) {
        const uint64_t read = BytesReadFrom(connection->socket).value_or(0);
        head_bytes = read - std::min(connection->read_at_phase, read);
      }
      const bool too_long = head_bytes > limits_.max_head_bytes;
      if (!late && !too_long) continue;
      closed.push_back(
          too_long ? absl::StrCat(connection->client, ": a request head over ",
                                  limits_.max_head_bytes, " bytes (",
                                  head_bytes, " read)")
                   : absl::StrCat(
                         connection->client, ": no complete request ",
                         connection->phase == Phase::kHead ? "head" : "body",
                         " within ",
                         absl::FormatDuration(connection->phase == Phase::kHead
                                                  ? limits_.head_timeout
                                                  : limits_.body_timeout)));
      connection->phase = Phase::kClosed;
      // The thread serving it sees the end of the stream and closes.
      ::shutdown(connection->socket, SHUT_RDWR);
    }
  }
  if (limits_.on_refused) {
    for (const std::string& reason : closed) limits_.on_refused(reason);
  }
}

void ConnectionGuard::shutdown() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (stopping_ && !deadlines_.joinable()) return;
    stopping_ = true;
    // Connections still waiting for a request are ended; handlers finish.
    for (const std::shared_ptr<Connection>& connection : open_) {
      if (connection->phase == Phase::kHead) {
        ::shutdown(connection->socket, SHUT_RDWR);
      }
    }
  }
  wake_.notify_all();
  if (deadlines_.joinable()) deadlines_.join();
  std::vector<std::thread> workers;
  {
    std::lock_guard<std::mutex> lock(mu_);
    workers.swap(workers_);
  }
  for (std::thread& worker : workers) worker.join();
  overflow_wake_.notify_all();
  std::thread overflow;
  {
    std::lock_guard<std::mutex> lock(mu_);
    overflow.swap(overflow_);
  }
  if (overflow.joinable()) overflow.join();
}

void ConnectionGuard::Mark(Phase phase) {
  auto* connection = static_cast<Connection*>(current);
  if (connection == nullptr) return;
  std::lock_guard<std::mutex> lock(connection->guard->mu_);
  if (connection->phase == Phase::kClosed) return;
  connection->since = absl::Now();
  connection->phase = phase;
  if (phase == Phase::kHead) {
    connection->read_at_phase = BytesReadFrom(connection->socket).value_or(0);
  }
}

void ConnectionGuard::HeadRead() { Mark(Phase::kBody); }
void ConnectionGuard::Handling() { Mark(Phase::kHandling); }

bool ConnectionGuard::PeerClosed() {
  auto* connection = static_cast<Connection*>(current);
  if (connection == nullptr || connection->socket < 0) return false;
  pollfd poll_fd{connection->socket, POLLRDHUP, 0};
  return ::poll(&poll_fd, 1, 0) > 0 &&
         (poll_fd.revents & (POLLRDHUP | POLLHUP | POLLERR)) != 0;
}
void ConnectionGuard::AnswerSent() {
  Mark(Phase::kHead);
  auto* connection = static_cast<Connection*>(current);
  if (connection != nullptr && connection->close_after_answer) {
    ::shutdown(connection->socket, SHUT_RDWR);
  }
}

void ConnectionGuard::CloseAfterAnswer() {
  auto* connection = static_cast<Connection*>(current);
  if (connection != nullptr) connection->close_after_answer = true;
}

}  // namespace fleetmem::http
