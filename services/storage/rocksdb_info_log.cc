#include "services/storage/rocksdb_info_log.h"

#include <cstdarg>
#include <cstdio>
#include <string>

#include "services/common/log.h"

namespace fleetmem::storage {
namespace {

log::Level ServerLevel(rocksdb::InfoLogLevel level) {
  switch (level) {
    case rocksdb::InfoLogLevel::WARN_LEVEL:
      return log::Level::kWarning;
    case rocksdb::InfoLogLevel::ERROR_LEVEL:
    case rocksdb::InfoLogLevel::FATAL_LEVEL:
      return log::Level::kError;
    default:  // DEBUG, INFO, HEADER: not written (Logv)
      return log::Level::kDebug;
  }
}

class ServerLogger : public rocksdb::Logger {
 public:
  ServerLogger() : rocksdb::Logger(rocksdb::InfoLogLevel::WARN_LEVEL) {}

  // RocksDB's unlevelled lines are info lines: filtered as those are.
  void Logv(const char* format, va_list ap) override {
    Logv(rocksdb::InfoLogLevel::INFO_LEVEL, format, ap);
  }
  void Logv(const rocksdb::InfoLogLevel level, const char* format,
            va_list ap) override {
    // HEADER_LEVEL ranks above FATAL in RocksDB's enum, but its lines are
    // the options dump at open: kept out like the info lines.
    if (level < GetInfoLogLevel() ||
        level == rocksdb::InfoLogLevel::HEADER_LEVEL) {
      return;
    }
    Write(level, format, ap);
  }
  void LogHeader(const char* format, va_list ap) override {
    Logv(rocksdb::InfoLogLevel::HEADER_LEVEL, format, ap);
  }

 private:
  // Never throws into RocksDB: a line that cannot be formatted is dropped.
  static void Write(rocksdb::InfoLogLevel level, const char* format,
                    va_list ap) {
    va_list measure;
    va_copy(measure, ap);
    const int size = std::vsnprintf(nullptr, 0, format, measure);
    va_end(measure);
    if (size <= 0) return;
    std::string line(static_cast<size_t>(size) + 1, '\0');
    std::vsnprintf(line.data(), line.size(), format, ap);
    line.resize(static_cast<size_t>(size));
    while (!line.empty() && line.back() == '\n') line.pop_back();
    // "… W rocksdb:0] <RocksDB's line>"
    log::Write(ServerLevel(level), "rocksdb", 0, line);
  }
};

}  // namespace

std::shared_ptr<rocksdb::Logger> NewRocksDbInfoLog() {
  return std::make_shared<ServerLogger>();
}

}  // namespace fleetmem::storage
