#include "clients/cli/trace_io.h"

#include <string>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "google/protobuf/util/json_util.h"

namespace fleetmem::cli {
namespace {

std::string ProtobufMessage(const google::protobuf::util::Status& status) {
  return std::string(status.message().data(), status.message().size());
}

}  // namespace

namespace {

// One `Message` per line (protobuf JSON); blank lines skipped.
template <typename Message>
absl::StatusOr<std::vector<Message>> ReadJsonl(std::istream& in,
                                               absl::string_view what) {
  std::vector<Message> messages;
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    if (absl::StripAsciiWhitespace(line).empty()) continue;
    Message message;
    const auto status =
        google::protobuf::util::JsonStringToMessage(line, &message);
    if (!status.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "line ", number, ": not a ", what, ": ", ProtobufMessage(status)));
    }
    messages.push_back(std::move(message));
  }
  if (in.bad()) return absl::DataLossError("read error");
  return messages;
}

}  // namespace

absl::StatusOr<std::vector<v1::MemoryTrace>> ReadTracesJsonl(std::istream& in) {
  return ReadJsonl<v1::MemoryTrace>(in, "MemoryTrace");
}

absl::StatusOr<std::vector<v1::RewardUpdate>> ReadRewardUpdatesJsonl(
    std::istream& in) {
  return ReadJsonl<v1::RewardUpdate>(in, "RewardUpdate");
}

absl::Status WriteTracesJsonl(std::span<const v1::MemoryTrace> traces,
                              std::ostream& out) {
  std::string json;
  for (const v1::MemoryTrace& trace : traces) {
    json.clear();
    const auto status = google::protobuf::util::MessageToJsonString(
        trace, &json, google::protobuf::util::JsonPrintOptions());
    if (!status.ok()) return absl::InternalError(status.ToString());
    out << json << '\n';
  }
  if (!out) return absl::DataLossError("write error");
  return absl::OkStatus();
}

absl::StatusOr<v1::QueryPlaceRequest> ParseQueryJson(absl::string_view json) {
  std::string object(absl::StripAsciiWhitespace(json));
  if (!object.empty() && object.front() == '[') {
    object = absl::StrCat("{\"code\": ", object, "}");
  }
  google::protobuf::util::JsonParseOptions options;
  options.ignore_unknown_fields = true;
  v1::QueryPlaceRequest request;
  const auto status =
      google::protobuf::util::JsonStringToMessage(object, &request, options);
  if (!status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("not a query code: ", ProtobufMessage(status)));
  }
  if (request.code().empty()) {
    return absl::InvalidArgumentError("no \"code\" array in the query");
  }
  return request;
}

}  // namespace fleetmem::cli
