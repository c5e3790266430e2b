#include "services/transport/upload_reactor.h"

#include <grpcpp/support/proto_buffer_reader.h>

#include <algorithm>
#include <chrono>
#include <memory>
#include <span>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/validation.h"
#include "services/transport/call_auth.h"
#include "services/transport/grpc_status.h"
#include "services/transport/memory_api.h"
#include "services/transport/proto_convert.h"
#include "services/transport/upload_checks.h"

namespace fleetmem::transport {

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

absl::StatusOr<v1::UploadTracesRequest*> ParseUploadMessage(
    const grpc::ByteBuffer& buffer, google::protobuf::Arena* arena) {
  auto* request =
      google::protobuf::Arena::CreateMessage<v1::UploadTracesRequest>(arena);
  grpc::ByteBuffer shared(buffer);  // the reader takes a mutable buffer
  grpc::ProtoBufferReader reader(&shared);
  if (!request->ParseFromZeroCopyStream(&reader)) {
    return absl::InvalidArgumentError(
        absl::StrCat(buffer.Length(),
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
  // Authenticated before a stream slot is taken, so that presenting a
  // robot's name without its secret cannot use up that robot's slots.
  absl::StatusOr<auth::Principal> caller =
      AuthenticateCall(state_->authenticator(), *context);
  if (!caller.ok()) {
    Done(ToGrpcStatus(caller.status()));
    return;
  }
  // An upload another replica forwards to this one (the fleet's owner) is
  // counted where the robot's stream is (max_streams_per_client), not
  // again here under the peer's name, which every forwarded upload shares.
  const bool forwarded =
      context->client_metadata().count(kForwardedHeader) > 0 &&
      caller->role == auth::Role::kAdmin;
  if (!forwarded) {
    std::string client = ClientName(state_->authenticator(), *context, *caller);
    if (absl::Status slot = state_->AcquireStream(client); !slot.ok()) {
      Done(ToGrpcStatus(slot));
      return;
    }
    client_ = std::move(client);
  }
  caller_ = *std::move(caller);
  absl::MutexLock lock(&mu_);
  MaybeRead();
}

std::string UploadReactor::Earlier(uint64_t index) const {
  if (index <= 1) return "; nothing of the stream was stored";
  return absl::StrCat("; messages 1..", index - 1, " are durable (",
                      totals_.accepted(), " accepted, ", totals_.duplicates(),
                      " duplicates)");
}

void UploadReactor::Fail(uint64_t index, const absl::Status& status,
                         std::string_view after) {
  // A refusal (bad traces, another encoder version, a robot id outside the
  // caller's rights, a quota) is the operator's business too: the client's
  // log is on the robot. Once per stream (the stream ends here).
  if (!absl::IsUnavailable(status) && !absl::IsCancelled(status) &&
      !absl::IsDeadlineExceeded(status)) {
    FLEETMEM_LOG(kWarning) << "UploadTraces refused: fleet \"" << fleet_id_
                           << "\", principal \"" << caller_.name << "\" at "
                           << context_->peer() << ": " << status;
  }
  Done(ToGrpcStatus(absl::Status(
      status.code(),
      absl::StrCat("message ", index, " of the stream: ", status.message(),
                   Earlier(index), V(after)))));
}

void UploadReactor::MaybeRead() {
  if (reading_ || closed_ || stop_reading_ || finished_ ||
      queue_.size() >= kReadAhead || queued_bytes_ >= kReadAheadBytes) {
    return;
  }
  reading_ = true;
  // The client has stream_idle_timeout to send its next message (or close
  // its side); a stream that sends nothing holds a slot and memory.
  idle_.Arm(state_->options().stream_idle_timeout,
            absl::StrCat("UploadTraces stream of ", client_),
            "no message for stream_idle_timeout");
  StartRead(&buffer_);
}

void UploadReactor::OnReadDone(bool ok) {
  {
    absl::MutexLock lock(&mu_);
    idle_.Disarm();
  }
  if (!ok) {
    // The client closed its side (or the call broke): once every message
    // read so far is stored, report the totals.
    bool finish = false;
    {
      absl::MutexLock lock(&mu_);
      reading_ = false;
      closed_ = true;
      finish = !storing_ && queue_.empty() && !finished_;
    }
    if (finish) {
      std::string answer = totals_.SerializeAsString();
      grpc::Slice slice(answer);
      *response_ = grpc::ByteBuffer(&slice, 1);
      Done(grpc::Status::OK);
    }
    return;
  }
  Message message;
  message.index = ++read_;
  message.bytes = buffer_.Length();
  if (state_->shutting_down()) {
    message.error = absl::UnavailableError(
        "the server is shutting down; nothing of this message was stored");
  } else {
    google::protobuf::ArenaOptions sizes;
    // About the parsed message's size: its codes are most of the bytes.
    sizes.start_block_size = std::max<size_t>(1024, message.bytes * 5 / 4);
    sizes.max_block_size = sizes.start_block_size;
    message.arena = std::make_unique<google::protobuf::Arena>(sizes);
    absl::StatusOr<v1::UploadTracesRequest*> parsed =
        ParseUploadMessage(buffer_, message.arena.get());
    if (!parsed.ok()) {
      message.error = parsed.status();
    } else {
      message.request = *parsed;
      message.error = CheckUploadFleet(*message.request, fleet_id_);
      if (message.error.ok() && fleet_id_.empty()) {
        // The stream binds its name and resolves it once, before any
        // store: an alias switched meanwhile moves the next stream, not
        // this one.
        fleet_id_ = message.request->fleet_id();
        MemoryApi::Resolved resolved =
            state_->api().Resolve(caller_, fleet_id_);
        target_ = std::move(resolved.fleet_id);
        caller_ = std::move(resolved.caller);
      }
      if (message.error.ok()) message.request->set_fleet_id(target_);
    }
  }
  buffer_.Clear();
  bool submit = false;
  {
    absl::MutexLock lock(&mu_);
    reading_ = false;
    if (finished_) return;
    if (!message.error.ok()) stop_reading_ = true;
    queued_bytes_ += message.bytes;
    queue_.push_back(std::move(message));
    MaybeRead();
    submit = !storing_;
    storing_ = true;
  }
  if (!submit) return;
  state_->BeginWork();
  if (!state_->work().TrySubmit([this] {
        ServiceState* state = state_;  // `this` may be gone after it
        StoreQueued();
        state->EndWork();
      })) {
    state_->EndWork();
    Done(ServerBusyStatus());
  }
}

void UploadReactor::StoreQueued() {
  while (true) {
    std::deque<Message> batch;
    {
      absl::MutexLock lock(&mu_);
      // Nothing but this task finishes the call while it runs (OnReadDone
      // finishes only when no task stores).
      if (queue_.empty()) {
        storing_ = false;
        if (!closed_ || reading_) {
          MaybeRead();
          return;
        }
        // The client's side is done and everything is stored.
      } else {
        batch.swap(queue_);
        queued_bytes_ = 0;
        MaybeRead();
      }
    }
    if (batch.empty()) {
      std::string answer = totals_.SerializeAsString();
      grpc::Slice slice(answer);
      *response_ = grpc::ByteBuffer(&slice, 1);
      Done(grpc::Status::OK);
      return;
    }
    if (!StoreBatch(batch)) return;
  }
}

bool UploadReactor::StoreBatch(std::deque<Message>& batch) {
  if (grpc::Status live = CheckCallLive(*context_); !live.ok()) {
    Done(live);
    return false;
  }
  // The messages to store: those before the first that failed (read,
  // authorisation), which then fails the stream once they are stored.
  std::vector<std::vector<core::MemoryTrace>> traces;
  std::vector<std::span<const core::MemoryTrace>> messages;
  size_t count = 0;
  uint64_t failed_index = 0;
  absl::Status failed;
  bool wait_applied = false;
  for (; count < batch.size(); ++count) {
    Message& message = batch[count];
    failed = message.error;
    if (failed.ok()) {
      absl::StatusOr<CheckedUpload> checked =
          CheckUploadTraces(caller_, *message.request);
      if (checked.ok()) {
        traces.push_back(std::move(checked->traces));
        wait_applied |= checked->wait_applied;
        continue;
      }
      failed = checked.status();
    }
    failed_index = message.index;
    break;
  }
  for (const std::vector<core::MemoryTrace>& one : traces) {
    messages.emplace_back(one);
  }
  UploadOptions options;
  options.wait_applied = wait_applied;
  options.deadline = absl::FromChrono(context_->deadline());
  options.forwarded = context_->client_metadata().count(kForwardedHeader) > 0;
  std::vector<absl::StatusOr<Uploaded>> results;
  if (!messages.empty()) {
    results = state_->memory().UploadMany(target_, messages, options);
  }
  for (size_t i = 0; i < results.size(); ++i) {
    if (!results[i].ok()) {
      // Messages after it in the same write may be stored too.
      uint64_t later = 0;
      for (size_t j = i + 1; j < results.size(); ++j) {
        if (results[j].ok()) ++later;
      }
      Fail(batch[i].index, results[i].status(),
           later == 0 ? ""
                      : absl::StrCat("; ", later,
                                     " messages after it were stored with it "
                                     "(duplicates when retried)"));
      return false;
    }
    const Uploaded& uploaded = *results[i];
    AddUploadResult(uploaded.result, &totals_);
    if (uploaded.sequence != 0) totals_.set_last_sequence(uploaded.sequence);
    // Every message so far applied before its answer.
    totals_.set_applied((stored_ == 0 || totals_.applied()) &&
                        uploaded.applied);
    ++stored_;
    if (state_->options().on_upload_bytes) {
      state_->options().on_upload_bytes(target_, batch[i].bytes);
    }
  }
  if (!failed.ok()) {
    Fail(failed_index, failed);
    return false;
  }
  return true;
}

void UploadReactor::Done(const grpc::Status& status) {
  {
    absl::MutexLock lock(&mu_);
    if (finished_) return;
    finished_ = true;
  }
  state_->ObserveCall("UploadTraces",
                      static_cast<absl::StatusCode>(status.error_code()),
                      started_);
  Finish(status);
}

void UploadReactor::OnDone() {
  {
    absl::MutexLock lock(&mu_);
    idle_.Detach();  // the context goes with this reactor
    idle_.Disarm();
  }
  if (!client_.empty()) state_->ReleaseStream(client_);
  delete this;
}

}  // namespace fleetmem::transport
