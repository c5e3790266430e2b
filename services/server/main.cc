// fleetmem-server: the composition root. Reads flags and the config file,
// opens RocksDB under DATA_DIR/db, loads every fleet into the engine, serves
// fleetmem.v1.MemoryService (plus health checking and reflection) and shuts
// down cleanly on SIGTERM or SIGINT.
//
// Exit codes: 0 after a clean shutdown or --help; 2 for bad flags or config;
// 1 if the server cannot start (storage, engine, address).
#include <pthread.h>
#include <signal.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <memory>
#include <string>
#include <system_error>
#include <utility>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "grpcpp/ext/proto_server_reflection_plugin.h"
#include "grpcpp/grpcpp.h"
#include "grpcpp/health_check_service_interface.h"
#include "services/common/log.h"
#include "services/engine/memory_engine.h"
#include "services/index/exact_index.h"
#include "services/index/flann_index.h"
#include "services/server/server_config.h"
#include "services/storage/rocksdb_store.h"
#include "services/transport/memory_service.h"
#include "services/transport/work_queue.h"

namespace fleetmem::server {
namespace {

constexpr char kServiceName[] = "fleetmem.v1.MemoryService";

engine::PlaceIndexFactory MakeIndexFactory(const ServerConfig& config) {
  switch (config.index) {
    case IndexKind::kFlann:
      return [options = config.flann](size_t dimension) {
        return index::NewFlannIndex(dimension, options);
      };
    case IndexKind::kExact:
      break;
  }
  return [](size_t dimension) { return index::NewExactIndex(dimension); };
}

// "host:port" with the port replaced by `port` (for listen port 0).
std::string WithPort(const std::string& listen, int port) {
  return listen.substr(0, listen.rfind(':') + 1) + std::to_string(port);
}

// Blocks SIGTERM and SIGINT in this thread and every thread it starts later
// (gRPC's, RocksDB's, the workers), so that only sigwait sees them.
sigset_t BlockShutdownSignals() {
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  return signals;
}

int Serve(const ServerConfig& config, const sigset_t& signals) {
  std::error_code error;
  std::filesystem::create_directories(config.data_dir, error);
  if (error) {
    FLEETMEM_LOG(kError) << "cannot create data dir " << config.data_dir << ": "
                         << error.message();
    return 1;
  }
  storage::RocksDbStoreOptions store_options = config.storage;
  store_options.path = (std::filesystem::path(config.data_dir) / "db").string();
  absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
      storage::OpenRocksDbStore(store_options);
  if (!store.ok()) {
    FLEETMEM_LOG(kError) << "cannot open store: " << store.status();
    return 1;
  }
  absl::StatusOr<std::unique_ptr<engine::MemoryEngine>> engine =
      engine::MemoryEngine::Open(config.engine, store->get(),
                                 MakeIndexFactory(config));
  if (!engine.ok()) {
    FLEETMEM_LOG(kError) << "cannot load fleets: " << engine.status();
    return 1;
  }
  transport::WorkQueue work(config.work);
  transport::MemoryServiceImpl service(engine->get(), &work);

  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort(config.listen, grpc::InsecureServerCredentials(),
                           &port);
  builder.SetMaxReceiveMessageSize(
      static_cast<int>(config.max_receive_message_bytes));
  builder.RegisterService(&service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (server == nullptr || port == 0) {
    FLEETMEM_LOG(kError) << "cannot listen on " << config.listen;
    work.Stop();
    return 1;
  }
  grpc::HealthCheckServiceInterface* health = server->GetHealthCheckService();
  health->SetServingStatus(kServiceName, true);
  health->SetServingStatus(true);

  const std::string address = WithPort(config.listen, port);
  FLEETMEM_LOG(kInfo) << "data dir " << config.data_dir << " (store "
                      << store_options.path << "), "
                      << (*engine)->ListFleets().size() << " fleets loaded";
  FLEETMEM_LOG(kInfo) << "options: " << DescribeConfig(config);
  FLEETMEM_LOG(kInfo) << "fleetmem-server listening on " << address;
  std::cout << "fleetmem-server listening on " << address << std::endl;

  int signal = 0;
  sigwait(&signals, &signal);
  FLEETMEM_LOG(kInfo) << "received "
                      << (signal == SIGINT ? "SIGINT" : "SIGTERM")
                      << ", shutting down (grace "
                      << config.shutdown_grace_seconds << " s)";
  health->SetServingStatus(kServiceName, false);
  health->SetServingStatus(false);
  service.Shutdown();  // new calls UNAVAILABLE, watches end
  server->Shutdown(std::chrono::system_clock::now() +
                   std::chrono::seconds(config.shutdown_grace_seconds));
  work.Stop();
  server.reset();
  engine->reset();
  store->reset();
  FLEETMEM_LOG(kInfo) << "stopped";
  return 0;
}

}  // namespace
}  // namespace fleetmem::server

int main(int argc, char** argv) {
  namespace server = fleetmem::server;
  const sigset_t signals = server::BlockShutdownSignals();
  absl::StatusOr<server::CommandLine> command_line =
      server::ParseCommandLine(argc, argv);
  if (!command_line.ok()) {
    std::cerr << "fleetmem-server: " << command_line.status().message()
              << "\nRun fleetmem-server --help for usage.\n";
    return 2;
  }
  if (command_line->help) {
    std::cout << server::Usage();
    return 0;
  }
  absl::StatusOr<server::ServerConfig> config =
      server::LoadServerConfig(*command_line);
  if (!config.ok()) {
    std::cerr << "fleetmem-server: " << config.status().message() << "\n";
    return 2;
  }
  fleetmem::log::SetLevel(config->log_level);
  return server::Serve(*config, signals);
}
