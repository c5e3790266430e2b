// The C++ client's upload, the peer of the Python client's in
// bench/python_upload_bench.py: reads N x D float32 codes (a raw
// little-endian file the Python script writes), makes the traces the way a
// C++ robot does (fleetmem.v1.MemoryTrace messages: code, place x = row,
// reward 1, seq = row) and uploads them with client::Client::Upload (one
// stream, upload_batch_size traces per message). Prints one JSON line:
// traces, seconds (conversion and upload, as the Python figure), rate.
//
//   fleetmem_client_upload_bench --server HOST:PORT --codes FILE --dim D
//       --fleet F --robot R [--ack durable|applied] [--batch 500]
#include <chrono>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "clients/cpp/fleetmem_client.h"
#include "services/common/cli_program.h"

int main(int argc, char** argv) {
  CLI::App app{
      "fleetmem_client_upload_bench: upload throughput of the C++ client "
      "(peer of the Python one)."};
  fleetmem::common::SetUpProgram(app, "fleetmem_client_upload_bench");
  std::string server, codes_file, fleet, robot, ack = "durable";
  size_t dim = 0, batch = 500;
  app.add_option("--server", server, "HOST:PORT")->required();
  app.add_option("--codes", codes_file, "raw float32 N x D")->required();
  app.add_option("--dim", dim, "D")->required();
  app.add_option("--fleet", fleet, "fleet to upload to")->required();
  app.add_option("--robot", robot, "robot id")->required();
  app.add_option("--ack", ack, "durable or applied")
      ->check(CLI::IsMember({"durable", "applied"}));
  app.add_option("--batch", batch, "traces per message");
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }

  std::ifstream in(codes_file, std::ios::binary | std::ios::ate);
  const size_t bytes = in ? static_cast<size_t>(in.tellg()) : 0;
  std::vector<float> codes(bytes / sizeof(float));
  in.seekg(0);
  in.read(reinterpret_cast<char*>(codes.data()),
          static_cast<std::streamsize>(bytes));
  if (!in || dim == 0 || codes.size() % dim != 0) {
    std::cerr << codes_file << ": cannot read N x " << dim << " floats\n";
    return 2;
  }
  const size_t n = codes.size() / dim;

  fleetmem::client::ClientOptions options;
  options.target = server;
  options.upload_batch_size = batch;
  options.deadline = std::chrono::seconds(120);
  options.upload_ack = ack == "applied" ? fleetmem::v1::UPLOAD_ACK_APPLIED
                                        : fleetmem::v1::UPLOAD_ACK_DURABLE;
  std::unique_ptr<fleetmem::client::Client> client =
      fleetmem::client::Client::Create(options);

  const auto start = std::chrono::steady_clock::now();
  std::vector<fleetmem::v1::MemoryTrace> traces(n);
  for (size_t i = 0; i < n; ++i) {
    fleetmem::v1::MemoryTrace& trace = traces[i];
    trace.set_robot_id(robot);
    trace.set_seq(i);
    trace.mutable_code()->Add(
        codes.begin() + static_cast<ptrdiff_t>(i * dim),
        codes.begin() + static_cast<ptrdiff_t>((i + 1) * dim));
    trace.mutable_pose()->set_x(static_cast<double>(i));
    trace.set_reward(1.0f);
  }
  auto uploaded = client->Upload(fleet, traces);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  if (!uploaded.ok()) {
    std::cerr << "upload failed: " << uploaded.status() << "\n";
    return 1;
  }
  std::cout << "{\"client\": \"cpp\", \"traces\": " << n
            << ", \"accepted\": " << uploaded->accepted()
            << ", \"seconds\": " << seconds
            << ", \"traces_per_s\": " << static_cast<double>(n) / seconds << "}"
            << std::endl;
  return 0;
}
