#include "tests/security_helpers.h"

#include <cstdlib>
#include <fstream>
#include <sstream>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "grpcpp/grpcpp.h"
#include "grpcpp/security/credentials.h"
#include "grpcpp/support/client_interceptor.h"
#include "tests/server_process.h"
#include "fleetmem_paths.h"

namespace fleetmem::testing {
namespace {

class TokenInterceptor : public grpc::experimental::Interceptor {
 public:
  explicit TokenInterceptor(std::string header) : header_(std::move(header)) {}
  void Intercept(
      grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(
            grpc::experimental::InterceptionHookPoints::
                PRE_SEND_INITIAL_METADATA)) {
      methods->GetSendInitialMetadata()->insert({"authorization", header_});
    }
    methods->Proceed();
  }

 private:
  std::string header_;
};

class TokenInterceptorFactory
    : public grpc::experimental::ClientInterceptorFactoryInterface {
 public:
  explicit TokenInterceptorFactory(std::string token)
      : header_("Bearer " + std::move(token)) {}
  grpc::experimental::Interceptor* CreateClientInterceptor(
      grpc::experimental::ClientRpcInfo*) override {
    return new TokenInterceptor(header_);
  }

 private:
  std::string header_;
};

}  // namespace

absl::Status RunCommand(const std::string& command) {
  const int status = std::system(command.c_str());
  if (status != 0) {
    return absl::InternalError(
        absl::StrCat("command failed (status ", status, "): ", command));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> AddPrincipal(const std::string& dir,
                                         const std::string& credentials_file,
                                         const std::string& name,
                                         const std::string& role,
                                         const std::vector<std::string>& fleets,
                                         const std::string& certificate_cn) {
  const std::string token_file = absl::StrCat(dir, "/", name, ".token");
  std::string command = absl::StrCat(
      FLEETMEM_BIN_DIR, "/fleetmem-credential --name ", name, " --role ", role);
  for (const std::string& fleet : fleets) {
    absl::StrAppend(&command, " --fleet '", fleet, "'");
  }
  if (!certificate_cn.empty()) {
    absl::StrAppend(&command, " --certificate-cn ", certificate_cn);
  } else {
    absl::StrAppend(&command, " --token-file ", token_file);
  }
  absl::StrAppend(&command, " >> ", credentials_file);
  if (absl::Status ran = RunCommand(command); !ran.ok()) return ran;
  if (!certificate_cn.empty()) return std::string();
  return std::string(absl::StripAsciiWhitespace(ReadFileOrEmpty(token_file)));
}

absl::Status MakeCertificates(const std::string& dir,
                              const std::vector<std::string>& client_cns) {
  const std::string quiet = " 2>/dev/null";
  auto ca = [&](const std::string& name, const std::string& cn) {
    return RunCommand(absl::StrCat(
        "cd ", dir, " && openssl req -x509 -newkey rsa:2048 -nodes -days 2",
        " -keyout ", name, ".key -out ", name, ".pem -subj '/CN=", cn, "'",
        quiet));
  };
  auto signed_by = [&](const std::string& ca_name, const std::string& name,
                       const std::string& cn, const std::string& san) {
    std::string ext;
    if (!san.empty()) {
      ext = absl::StrCat(" -extfile ", name, ".ext");
      std::ofstream(absl::StrCat(dir, "/", name, ".ext"))
          << "subjectAltName=" << san << "\n";
    }
    return RunCommand(absl::StrCat(
        "cd ", dir, " && openssl req -newkey rsa:2048 -nodes -keyout ", name,
        ".key -out ", name, ".csr -subj '/CN=", cn, "'", quiet,
        " && openssl x509 -req -in ", name, ".csr -CA ", ca_name,
        ".pem -CAkey ", ca_name, ".key -CAcreateserial -days 2 -out ", name,
        ".pem", ext, quiet));
  };
  absl::Status status = ca("ca", "fleetmem test CA");
  if (status.ok()) {
    status =
        signed_by("ca", "server", "localhost", "DNS:localhost,IP:127.0.0.1");
  }
  for (const std::string& cn : client_cns) {
    if (status.ok()) status = signed_by("ca", "client-" + cn, cn, "");
  }
  if (status.ok()) status = ca("rogue-ca", "rogue CA");
  if (status.ok())
    status = signed_by("rogue-ca", "rogue-client", "robot-8", "");
  if (status.ok()) {
    status = signed_by("rogue-ca", "server-renewed", "localhost",
                       "DNS:localhost,IP:127.0.0.1");
  }
  return status;
}

std::unique_ptr<v1::MemoryService::Stub> MakeSecureStub(
    const std::string& address, const ChannelSecurity& security) {
  std::shared_ptr<grpc::ChannelCredentials> credentials =
      grpc::InsecureChannelCredentials();
  if (!security.ca_pem.empty()) {
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = security.ca_pem;
    ssl.pem_cert_chain = security.cert_pem;
    ssl.pem_private_key = security.key_pem;
    credentials = grpc::SslCredentials(ssl);
  }
  grpc::ChannelArguments arguments;
  arguments.SetMaxReceiveMessageSize(64 << 20);
  if (security.own_connection) {
    arguments.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  }
  std::vector<
      std::unique_ptr<grpc::experimental::ClientInterceptorFactoryInterface>>
      interceptors;
  if (!security.token.empty()) {
    interceptors.push_back(
        std::make_unique<TokenInterceptorFactory>(security.token));
  }
  return v1::MemoryService::NewStub(
      grpc::experimental::CreateCustomChannelWithInterceptors(
          address, credentials, arguments, std::move(interceptors)));
}

}  // namespace fleetmem::testing
