// Levelled logging to stderr: "2026-11-21T10:00:00.123Z I file.cc:42] msg".
// Thread-safe. The level is set once by the server's main.
#ifndef FLEETMEM_SERVICES_COMMON_LOG_H_
#define FLEETMEM_SERVICES_COMMON_LOG_H_

#include <sstream>
#include <string_view>

namespace fleetmem::log {

enum class Level { kDebug = 0, kInfo = 1, kWarning = 2, kError = 3 };

void SetLevel(Level level);
Level GetLevel();
// "debug", "info", "warning", "error"; false if unknown.
bool ParseLevel(std::string_view text, Level* level);

// Writes one line if `level` is enabled.
void Write(Level level, const char* file, int line, std::string_view message);

// Collects a message with << and writes it when destroyed.
class Line {
 public:
  Line(Level level, const char* file, int line)
      : level_(level), file_(file), line_(line) {}
  ~Line() { Write(level_, file_, line_, stream_.str()); }
  template <typename T>
  Line& operator<<(const T& value) {
    stream_ << value;
    return *this;
  }

 private:
  Level level_;
  const char* file_;
  int line_;
  std::ostringstream stream_;
};

}  // namespace fleetmem::log

#define FLEETMEM_LOG(level)                                               \
  if (::fleetmem::log::Level::level < ::fleetmem::log::GetLevel()) {      \
  } else                                                                  \
    ::fleetmem::log::Line(::fleetmem::log::Level::level, __FILE__, __LINE__)

#endif  // FLEETMEM_SERVICES_COMMON_LOG_H_
