// fleetmem-credential: makes a new principal for fleetmem-server's
// credentials file. Prints its `principal { ... }` entry (with the Argon2id
// hash of a fresh random secret) on stdout, to append to the server's
// --auth-file, and writes the client's token "NAME:SECRET" to --token-file
// (mode 0600; it is never printed). With only --certificate-cn, the
// principal authenticates by client certificate and no token is made.
//
//   fleetmem-credential --name robot-7 --role robot --fleet nordland \
//       --token-file robot-7.token >> credentials.textproto
//   kill -HUP $(pidof fleetmem-server)
//
// Exit codes: 0 done; 2 bad flags; 1 the token file cannot be written.
#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <iostream>
#include <optional>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "services/auth/authenticator.h"
#include "services/auth/secret.h"
#include "services/common/cli_program.h"

namespace {

// Writes `text` to a new file readable by its owner only.
bool WriteTokenFile(const std::string& path, const std::string& text) {
  const int fd = open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL, 0600);
  if (fd < 0) {
    std::cerr << "fleetmem-credential: cannot create " << path << ": "
              << std::strerror(errno) << "\n";
    return false;
  }
  const std::string line = text + "\n";
  const bool ok = write(fd, line.data(), line.size()) ==
                      static_cast<ssize_t>(line.size()) &&
                  fsync(fd) == 0;
  if (!ok) {
    std::cerr << "fleetmem-credential: cannot write " << path << ": "
              << std::strerror(errno) << "\n";
  }
  close(fd);
  return ok;
}

std::string Quoted(const std::string& text) { return "\"" + text + "\""; }

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "fleetmem-credential: makes a principal for fleetmem-server's "
      "--auth-file: prints its entry and writes its token file."};
  fleetmem::common::SetUpProgram(app, "fleetmem-credential");
  std::string name, role, robot_id, common_name, token_file;
  std::vector<std::string> fleets;
  app.add_option("--name", name, "principal name, e.g. robot-7")->required();
  app.add_option("--role", role, "robot, reader or admin")
      ->required()
      ->check(CLI::IsMember({"robot", "reader", "admin"}));
  app.add_option("--robot-id", robot_id,
                 "robot id a robot uploads as (default: --name)");
  app.add_option("--fleet", fleets, "fleet it belongs to (repeat; * = all)");
  app.add_option("--certificate-cn", common_name,
                 "common name of its client certificate (mutual TLS)");
  app.add_option("--token-file", token_file,
                 "new file for the token NAME:SECRET (mode 0600)");
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  if (token_file.empty() && common_name.empty()) {
    std::cerr << fleetmem::common::UsageErrorText(
        "fleetmem-credential", "give --token-file, --certificate-cn or both");
    return fleetmem::common::kExitUsage;
  }
  std::string entry =
      absl::StrCat("principal {\n  name: ", Quoted(name), "\n  role: ");
  for (char& c : role) c = static_cast<char>(std::toupper(c));
  absl::StrAppend(&entry, role, "\n");
  if (!robot_id.empty()) {
    absl::StrAppend(&entry, "  robot_id: ", Quoted(robot_id), "\n");
  }
  for (const std::string& fleet : fleets) {
    absl::StrAppend(&entry, "  fleets: ", Quoted(fleet), "\n");
  }
  if (!common_name.empty()) {
    absl::StrAppend(&entry, "  certificate_common_name: ", Quoted(common_name),
                    "\n");
  }
  if (!token_file.empty()) {
    absl::StatusOr<std::string> secret = fleetmem::auth::NewSecret();
    absl::StatusOr<std::string> hash =
        secret.ok() ? fleetmem::auth::HashSecret(*secret) : secret.status();
    if (!hash.ok()) {
      std::cerr << "fleetmem-credential: " << hash.status() << "\n";
      return 1;
    }
    absl::StrAppend(&entry, "  secret_hash: ", Quoted(*hash), "\n");
    if (!WriteTokenFile(token_file, fleetmem::auth::MakeToken(name, *secret))) {
      return 1;
    }
  }
  absl::StrAppend(&entry, "}\n");
  // The entry must be one the server accepts.
  absl::StatusOr<std::vector<fleetmem::auth::CredentialEntry>> check =
      fleetmem::auth::ParseCredentials(entry);
  if (!check.ok()) {
    std::cerr << "fleetmem-credential: " << check.status().message() << "\n";
    if (!token_file.empty()) unlink(token_file.c_str());
    return 2;
  }
  std::cout << entry;
  return 0;
}
