#include "services/transport/upload_reactor.h"

#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "services/common/log.h"
#include "services/core/validation.h"
#include "services/transport/call_auth.h"
#include "services/transport/grpc_status.h"
#include "services/transport/proto_convert.h"

namespace fleetmem::transport {
namespace {

// The bytes of a received message, in one string.
std::string Flatten(const grpc::ByteBuffer& buffer) {
  std::vector<grpc::Slice> slices;
  std::string out;
  if (!buffer.Dump(&slices).ok()) return out;
  out.reserve(buffer.Length());
  for (const grpc::Slice& slice : slices) {
    out.append(reinterpret_cast<const char*>(slice.begin()), slice.size());
  }
  return out;
}

}  // namespace

absl::StatusOr<v1::UploadTracesRequest> ParseUploadMessage(
    absl::string_view bytes) {
  v1::UploadTracesRequest request;
  if (!request.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
    return absl::InvalidArgumentError(
        absl::StrCat(bytes.size(),
                     " bytes do not parse as fleetmem.v1.UploadTracesRequest"));
  }
  return request;
}

UploadReactor::UploadReactor(ServiceState* state,
                             grpc::CallbackServerContext* context,
                             grpc::ByteBuffer* response)
    : state_(state), context_(context), response_(response) {
  if (state_->shutting_down()) {
    Done(ShuttingDownStatus());
    return;
  }
  std::string client = ClientName(*context);
  if (absl::Status slot = state_->AcquireStream(client); !slot.ok()) {
    Done(ToGrpcStatus(slot));
    return;
  }
  client_ = std::move(client);
  StartRead(&buffer_);
}

std::string UploadReactor::Earlier() const {
  if (index_ <= 1) return "; nothing of the stream was stored";
  return absl::StrCat("; messages 1..", index_ - 1, " are durable (",
                      totals_.accepted(), " accepted, ", totals_.duplicates(),
                      " duplicates)");
}

void UploadReactor::Fail(const absl::Status& status) {
  // A refusal (bad traces, another encoder version, a robot id outside the
  // caller's rights, a quota) is the operator's business too: the client's
  // log is on the robot. Once per stream (the stream ends here).
  if (!absl::IsUnavailable(status) && !absl::IsCancelled(status) &&
      !absl::IsDeadlineExceeded(status)) {
    FLEETMEM_LOG(kWarning) << "UploadTraces refused: fleet \"" << fleet_id_
                           << "\", "
                           << (principal_.has_value()
                                   ? "principal " + principal_->name
                                   : std::string("unauthenticated"))
                           << " at " << context_->peer() << ": " << status;
  }
  Done(ToGrpcStatus(absl::Status(
      status.code(), absl::StrCat("message ", index_, " of the stream: ",
                                  status.message(), Earlier()))));
}

void UploadReactor::OnReadDone(bool ok) {
  if (!ok) {
    // The client closed its side (or the call broke): every message read so
    // far is durable, so report the totals.
    std::string answer = totals_.SerializeAsString();
    grpc::Slice slice(answer);
    *response_ = grpc::ByteBuffer(&slice, 1);
    Done(grpc::Status::OK);
    return;
  }
  ++index_;
  if (state_->shutting_down()) {
    Done(ShuttingDownStatus());
    return;
  }
  const std::string bytes = Flatten(buffer_);
  message_bytes_ = bytes.size();
  absl::StatusOr<v1::UploadTracesRequest> parsed = ParseUploadMessage(bytes);
  buffer_.Clear();
  if (!parsed.ok()) {
    Fail(parsed.status());
    return;
  }
  request_ = std::move(*parsed);
  if (fleet_id_.empty()) {
    absl::Status valid = core::ValidateId("fleet_id", request_.fleet_id());
    if (!valid.ok()) {
      Fail(valid);
      return;
    }
    fleet_id_ = request_.fleet_id();
  } else if (request_.fleet_id() != fleet_id_) {
    Fail(absl::InvalidArgumentError(
        absl::StrCat("fleet_id: every message of an UploadTraces stream must "
                     "name the same fleet; got \"",
                     request_.fleet_id(), "\" after \"", fleet_id_, "\"")));
    return;
  }
  state_->BeginWork();
  if (!state_->work().TrySubmit([this] {
        ServiceState* state = state_;  // `this` may be gone after Store()
        Store();
        state->EndWork();
      })) {
    state_->EndWork();
    Done(ServerBusyStatus());
  }
}

void UploadReactor::Store() {
  grpc::Status live = CheckCallLive(*context_);
  if (!live.ok()) {
    Done(live);
    return;
  }
  if (!principal_.has_value()) {
    absl::StatusOr<auth::Principal> principal = AuthorizeCall(
        state_->authenticator(), *context_, auth::Action::kUpload, fleet_id_);
    if (!principal.ok()) {
      Fail(principal.status());
      return;
    }
    principal_ = std::move(*principal);
  }
  for (int i = 0; i < request_.traces_size(); ++i) {
    absl::Status allowed =
        auth::AuthorizeUploadAs(*principal_, request_.traces(i).robot_id());
    if (!allowed.ok()) {
      Fail(absl::PermissionDeniedError(
          absl::StrCat("traces[", i, "]: ", allowed.message())));
      return;
    }
  }
  std::vector<core::MemoryTrace> traces =
      UploadedTracesFromProto(request_.traces());
  UploadOptions options;
  options.wait_applied = request_.ack() == v1::UPLOAD_ACK_APPLIED;
  options.deadline = absl::FromChrono(context_->deadline());
  absl::StatusOr<Uploaded> uploaded =
      state_->memory().Upload(fleet_id_, traces, options);
  if (!uploaded.ok()) {
    Fail(uploaded.status());
    return;
  }
  AddUploadResult(uploaded->result, &totals_);
  if (uploaded->sequence != 0) totals_.set_last_sequence(uploaded->sequence);
  // Every message so far applied before its answer.
  totals_.set_applied((index_ == 1 || totals_.applied()) && uploaded->applied);
  if (state_->options().on_upload_bytes) {
    state_->options().on_upload_bytes(fleet_id_, message_bytes_);
  }
  StartRead(&buffer_);
}

void UploadReactor::Done(const grpc::Status& status) {
  state_->ObserveCall("UploadTraces",
                      static_cast<absl::StatusCode>(status.error_code()),
                      started_);
  Finish(status);
}

void UploadReactor::OnDone() {
  if (!client_.empty()) state_->ReleaseStream(client_);
  delete this;
}

}  // namespace fleetmem::transport
