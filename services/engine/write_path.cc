#include "services/engine/write_path.h"

#include <algorithm>
#include <iterator>
#include <optional>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "services/common/background_thread.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/engine/admission.h"

namespace fleetmem::engine {
namespace {

// Log entries read per page while recovering a log's tail.
constexpr size_t kRecoveryPage = 256;

// The last sequence s such that every entry in (after, s] is in `lost`.
uint64_t LostFrom(std::vector<LostLogEntries> lost, uint64_t after) {
  std::sort(lost.begin(), lost.end(),
            [](const LostLogEntries& a, const LostLogEntries& b) {
              return a.first < b.first;
            });
  for (const LostLogEntries& range : lost) {
    if (range.first > after + 1) break;
    after = std::max(after, range.last);
  }
  return after;
}

}  // namespace

absl::Status ValidateWritePathOptions(const WritePathOptions& options) {
  if (options.appliers < 1 || options.appliers > 64) {
    return absl::InvalidArgumentError(
        absl::StrCat("appliers must be 1..64, got ", options.appliers));
  }
  if (options.applier_nice < 0 || options.applier_nice > 19) {
    return absl::InvalidArgumentError(
        absl::StrCat("applier_nice must be 0..19, got ", options.applier_nice));
  }
  if (options.apply_batch < 1) {
    return absl::InvalidArgumentError("apply_batch must be at least 1");
  }
  if (options.retry_interval <= absl::ZeroDuration()) {
    return absl::InvalidArgumentError("retry_interval must be positive");
  }
  return absl::OkStatus();
}

// One upload waiting for the group commit.
struct WritePath::Request {
  std::span<const core::MemoryTrace> traces;
  // A call's record (AppendCall) instead of traces.
  std::optional<LogRecord> call;
  bool track = false;
  // The traces appended: `traces`, or the copies in `kept` when some were
  // duplicates.
  std::span<const core::MemoryTrace> accepted;
  std::vector<core::MemoryTrace> kept;
  // A replicated log's entries of `accepted` (WritePathOptions::replicated).
  std::vector<LogPiece> pieces;
  absl::StatusOr<Appended> result = absl::UnknownError("not admitted");
  bool done = false;
};

struct WritePath::FleetWrites {
  explicit FleetWrites(std::string fleet_id) : id(std::move(fleet_id)) {}

  const std::string id;
  absl::Mutex mu;
  // Signalled when applied_through grows, a group commit ends, or on Stop.
  absl::CondVar changed;

  // The group commit: uploads waiting, and whether one of them leads.
  std::vector<Request*> queue ABSL_GUARDED_BY(mu);
  bool leading ABSL_GUARDED_BY(mu) = false;
  bool stopped ABSL_GUARDED_BY(mu) = false;
  // Why, once stopped: what an upload still queued is answered.
  absl::Status closed ABSL_GUARDED_BY(mu);

  // The log's acknowledged entries not applied yet, in order.
  struct Entry {
    uint64_t sequence = 0;
    uint64_t traces = 0;
    absl::Time appended;
    std::shared_ptr<AppliedRecord> applied;  // for a caller that waits
  };
  std::deque<Entry> unapplied ABSL_GUARDED_BY(mu);
  uint64_t backlog_traces ABSL_GUARDED_BY(mu) = 0;
  uint64_t appended_through ABSL_GUARDED_BY(mu) = 0;
  uint64_t applied_through ABSL_GUARDED_BY(mu) = 0;
  absl::Status apply_error ABSL_GUARDED_BY(mu);
  // Applies that failed on the store (a caller of WaitApplied hears of
  // those made after it began to wait).
  uint64_t apply_failures ABSL_GUARDED_BY(mu) = 0;
  // In the appliers' queue, or being applied.
  bool scheduled ABSL_GUARDED_BY(mu) = false;

  // The admission's state: read and written by the group's leader only
  // (one at a time; `mu` orders one leader after the next) and by Recover
  // before any leader.
  std::optional<FleetShape> shape;
  uint64_t next_sequence = 1;
  // Every seq admitted per robot (received by the engine or in the log),
  // loaded at a robot's first upload since Open.
  absl::flat_hash_map<std::string, core::SeqSet> admitted;
  // The seqs of the log's tail found at Open, per robot, until the robot's
  // set is loaded.
  absl::flat_hash_map<std::string, core::SeqSet> recovered;
  // The engine's position in the log at Open: entries through it were
  // applied before (damage to them loses nothing). Set by Recover only.
  uint64_t opened_at = 0;
  // A DeleteFleet was appended since Open (or found in the tail): the
  // engine's received seqs are not the fleet's any more.
  bool remade = false;
  // Put before a replicated log's entry ids after a DeleteFleet ("d" and
  // the delete's sequence), so that a robot's seqs uploaded again to the
  // new fleet are not dropped as repeats of the deleted fleet's entries
  // (JetStream's duplicate window).
  std::string id_tag;
};

std::vector<std::string> BacklogWarnings(
    const std::vector<std::pair<std::string, Backlog>>& backlogs) {
  std::vector<std::string> lines;
  for (const auto& [fleet_id, backlog] : backlogs) {
    for (const LostLogEntries& lost : backlog.lost) {
      lines.push_back(absl::StrFormat(
          "DATA_LOSS fleet \"%s\": acknowledged log entries %d..%d are "
          "lost (%s)",
          fleet_id, lost.first, lost.last, lost.detail));
    }
    if (!backlog.apply_error.ok() && backlog.entries > 0) {
      lines.push_back(absl::StrFormat(
          "STUCK fleet \"%s\": %d acknowledged traces (%d log entries, the "
          "oldest %.0f s old) wait to be applied and are not seen by reads: "
          "%s",
          fleet_id, backlog.traces, backlog.entries, backlog.oldest_seconds,
          backlog.apply_error.ToString()));
    }
  }
  return lines;
}

WritePath::WritePath(WritePathOptions options, MemoryEngine* engine,
                     FleetLog* log)
    : options_(std::move(options)),
      engine_(engine),
      log_(log),
      applier_(log, engine) {}

WritePath::~WritePath() { Stop(); }

absl::StatusOr<std::unique_ptr<WritePath>> WritePath::Open(
    WritePathOptions options, MemoryEngine* engine, FleetLog* log) {
  if (absl::Status valid = ValidateWritePathOptions(options); !valid.ok()) {
    return valid;
  }
  std::unique_ptr<WritePath> path(
      new WritePath(std::move(options), engine, log));
  // The owner's logs are applied and recovered by the cluster (Own).
  if (path->options_.replicated.has_value()) return path;
  if (absl::Status recovered = path->Recover(); !recovered.ok()) {
    return recovered;
  }
  for (int i = 0; i < path->options_.appliers; ++i) {
    path->appliers_.emplace_back([p = path.get()] { p->RunApplier(); });
  }
  std::vector<FleetWrites*> waiting;
  {
    absl::MutexLock lock(&path->logs_mu_);
    for (auto& [fleet_id, log] : path->logs_) waiting.push_back(log.get());
  }
  for (FleetWrites* log : waiting) path->Schedule(*log);
  return path;
}

absl::Status WritePath::Recover() {
  const std::vector<std::string> fleets = engine_->ListFleets();
  for (const std::string& fleet_id : fleets) {
    absl::StatusOr<uint64_t> position = engine_->LogPosition(fleet_id);
    if (!position.ok()) return position.status();
    FleetWrites& log = *Log(fleet_id);
    log.shape = engine_->Shape(fleet_id);
    log.next_sequence = *position + 1;
    log.opened_at = *position;
    absl::MutexLock lock(&log.mu);
    log.appended_through = log.applied_through = *position;
  }
  absl::StatusOr<std::vector<std::string>> logged = log_->Fleets();
  if (!logged.ok()) return logged.status();
  uint64_t created = 0;  // fleets whose first upload waits in their log
  for (const std::string& fleet_id : *logged) {
    absl::StatusOr<LogBounds> bounds = log_->Bounds(fleet_id);
    if (!bounds.ok()) return bounds.status();
    absl::StatusOr<uint64_t> position = engine_->LogPosition(fleet_id);
    if (!position.ok()) return position.status();
    absl::StatusOr<bool> recovered =
        RecoverTail(*Log(fleet_id), *position, bounds->last);
    if (!recovered.ok()) return recovered.status();
    if (*recovered) ++created;
    // Entries the engine applied before the crash, but not trimmed yet.
    if (absl::Status trimmed = log_->Trim(fleet_id, *position); !trimmed.ok()) {
      FLEETMEM_LOG(kWarning)
          << "fleet \"" << fleet_id
          << "\": applied log entries not trimmed: " << trimmed;
    }
  }
  absl::MutexLock lock(&logs_mu_);
  fleets_ = fleets.size() + created;
  return absl::OkStatus();
}

absl::StatusOr<WritePath::FleetWrites*> WritePath::Adopt(
    std::string_view fleet_id) {
  const std::optional<FleetShape> shape = engine_->Shape(fleet_id);
  if (!shape.has_value()) return FleetNotFound(fleet_id);
  absl::StatusOr<uint64_t> position = engine_->LogPosition(fleet_id);
  if (!position.ok()) return position.status();
  absl::MutexLock lock(&logs_mu_);
  std::shared_ptr<FleetWrites>& made = logs_[std::string(fleet_id)];
  if (made != nullptr) return made.get();  // by another call meanwhile
  made = std::make_shared<FleetWrites>(std::string(fleet_id));
  FleetWrites& log = *made;
  log.shape = shape;
  log.next_sequence = *position + 1;
  log.opened_at = *position;
  ++fleets_;
  absl::MutexLock writes(&log.mu);
  log.appended_through = log.applied_through = *position;
  return &log;
}

absl::StatusOr<bool> WritePath::RecoverTail(FleetWrites& log, uint64_t position,
                                            uint64_t last) {
  const std::string& fleet_id = log.id;
  const bool had_shape = log.shape.has_value();
  const absl::Time now = absl::Now();
  uint64_t after = position;
  uint64_t traces = 0;
  std::deque<FleetWrites::Entry> entries;
  while (true) {
    absl::StatusOr<std::vector<LogEntry>> page =
        log_->Read(fleet_id, after, kRecoveryPage);
    if (!page.ok()) return page.status();
    for (const LogEntry& entry : *page) {
      const std::span<const core::MemoryTrace> logged = entry.traces();
      if (std::holds_alternative<DeleteFleetRecord>(entry.record)) {
        // What follows makes the fleet anew.
        log.shape.reset();
        log.recovered.clear();
        log.remade = true;
        log.id_tag = absl::StrCat("d", entry.sequence, "/");
      }
      if (!log.shape.has_value()) log.shape = ShapeOfEntry(entry);
      for (const core::MemoryTrace& trace : logged) {
        log.recovered[trace.robot_id].Insert(trace.seq);
      }
      entries.push_back({entry.sequence, logged.size(), now, nullptr});
      traces += logged.size();
      after = entry.sequence;
    }
    if (page->size() < kRecoveryPage) break;
  }
  log.next_sequence = std::max(last, position) + 1;
  FLEETMEM_LOG(kInfo) << "fleet \"" << fleet_id << "\": " << entries.size()
                      << " acknowledged log entries (" << traces
                      << " traces) after position " << position << " to apply";
  log.opened_at = position;
  ReportLosses(fleet_id, position);
  absl::MutexLock lock(&log.mu);
  log.appended_through = log.next_sequence - 1;
  // What the log no longer holds after the engine's position was applied
  // (entries are trimmed only once applied): a call's entry or a refused
  // upload's, which leave the engine's position where it was.
  log.applied_through =
      entries.empty() ? log.appended_through : entries.front().sequence - 1;
  log.unapplied = std::move(entries);
  log.backlog_traces = traces;
  return !had_shape && log.shape.has_value();
}

void WritePath::ReportLosses(const std::string& fleet_id, uint64_t position) {
  for (const LostLogEntries& lost : log_->Losses(fleet_id)) {
    if (lost.last <= position) {
      FLEETMEM_LOG(kWarning)
          << "fleet \"" << fleet_id << "\": log entries " << lost.first << ".."
          << lost.last << " are damaged but were applied before: "
          << "nothing is lost (" << lost.detail << ")";
      continue;
    }
    FLEETMEM_LOG(kError) << "fleet \"" << fleet_id
                         << "\": DATA_LOSS, acknowledged log entries "
                         << std::max(lost.first, position + 1) << ".."
                         << lost.last
                         << " are damaged and will not be applied: "
                         << lost.detail;
  }
}

std::shared_ptr<WritePath::FleetWrites> WritePath::Find(
    std::string_view fleet_id) const {
  absl::ReaderMutexLock lock(&logs_mu_);
  auto it = logs_.find(V(fleet_id));
  return it == logs_.end() ? nullptr : it->second;
}

WritePath::FleetWrites* WritePath::Log(std::string_view fleet_id) {
  if (std::shared_ptr<FleetWrites> log = Find(fleet_id)) return log.get();
  absl::MutexLock lock(&logs_mu_);
  auto& log = logs_[std::string(fleet_id)];
  if (log == nullptr) {
    log = std::make_shared<FleetWrites>(std::string(fleet_id));
  }
  return log.get();
}

absl::Status WritePath::Own(std::string_view fleet_id, uint64_t position) {
  if (Find(fleet_id) != nullptr) return absl::OkStatus();
  absl::StatusOr<LogBounds> bounds = log_->Bounds(fleet_id);
  if (!bounds.ok()) return bounds.status();
  auto made = std::make_shared<FleetWrites>(std::string(fleet_id));
  made->shape = engine_->Shape(fleet_id);
  absl::StatusOr<bool> recovered = RecoverTail(*made, position, bounds->last);
  if (!recovered.ok()) return recovered.status();
  if (!made->shape.has_value()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "fleet \"", V(fleet_id), "\" has no upload in its log after entry ",
        position, " and none applied: it is created by its first upload"));
  }
  absl::MutexLock lock(&logs_mu_);
  logs_.try_emplace(std::string(fleet_id), std::move(made));
  return absl::OkStatus();
}

void WritePath::Applied(std::string_view fleet_id, uint64_t sequence) {
  std::shared_ptr<FleetWrites> log = Find(fleet_id);
  if (log == nullptr) return;
  {
    absl::MutexLock lock(&log->mu);
    if (sequence <= log->applied_through) return;
  }
  MarkApplied(*log, sequence, AppliedRecord{});
}

void WritePath::Disown(std::string_view fleet_id) {
  std::shared_ptr<FleetWrites> log;
  {
    absl::MutexLock lock(&logs_mu_);
    auto it = logs_.find(V(fleet_id));
    if (it == logs_.end()) return;
    log = std::move(it->second);
    logs_.erase(it);
  }
  absl::MutexLock lock(&log->mu);
  log->stopped = true;
  log->closed = absl::UnavailableError(absl::StrCat(
      "fleet \"", V(fleet_id),
      "\" is no longer owned here (ownership moved); nothing of this upload "
      "was stored: retry"));
  log->changed.SignalAll();
}

absl::StatusOr<Appended> WritePath::Append(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
    bool track) {
  const std::span<const core::MemoryTrace> uploads[] = {traces};
  return std::move(AppendMany(fleet_id, uploads, track).front());
}

absl::StatusOr<Appended> WritePath::AppendCall(std::string_view fleet_id,
                                               const LogRecord& call) {
  if (std::holds_alternative<UploadRecord>(call)) {
    return absl::InvalidArgumentError(
        "WritePath::AppendCall takes a call's record, not an upload's");
  }
  {
    absl::MutexLock lock(&ready_mu_);
    if (stopping_) {
      return absl::UnavailableError(
          "the server is shutting down; the call was not logged");
    }
  }
  std::shared_ptr<FleetWrites> held = Find(fleet_id);
  FleetWrites* log = held.get();
  if (log == nullptr && options_.replicated.has_value()) {
    return absl::UnavailableError(absl::StrCat(
        "fleet \"", V(fleet_id),
        "\" is not owned here (ownership moved); the call was not logged: "
        "retry"));
  }
  if (log == nullptr) {
    // A fleet the engine holds that this write path has not met since it
    // opened (written into the engine directly: a restored image).
    absl::StatusOr<FleetWrites*> adopted = Adopt(fleet_id);
    if (!adopted.ok()) return adopted.status();
    log = *adopted;
  }
  Request request;
  request.call = call;
  request.track = true;
  absl::MutexLock lock(&log->mu);
  log->queue.push_back(&request);
  Commit(*log, std::span<Request>(&request, 1));
  return std::move(request.result);
}

absl::StatusOr<Appended> WritePath::AppendCreate(
    std::string_view fleet_id, const CreateFleetRecord& create) {
  if (options_.replicated.has_value()) {
    return absl::InternalError(
        "a replicated write path does not create fleets (the receiving "
        "replica appends their first entries)");
  }
  {
    absl::MutexLock lock(&ready_mu_);
    if (stopping_) {
      return absl::UnavailableError(
          "the server is shutting down; the fleet was not created");
    }
  }
  absl::Status valid =
      engine_->quota().AdmitDimension(fleet_id, create.code_dimension);
  if (valid.ok() && Find(fleet_id) == nullptr) {
    absl::ReaderMutexLock lock(&logs_mu_);
    valid = engine_->quota().AdmitNewFleet(fleet_id, fleets_);
  }
  if (!valid.ok()) return valid;
  FleetWrites* log = Log(fleet_id);
  Request request;
  request.call = create;
  request.track = true;
  absl::MutexLock lock(&log->mu);
  log->queue.push_back(&request);
  Commit(*log, std::span<Request>(&request, 1));
  return std::move(request.result);
}

void WritePath::Commit(FleetWrites& log, std::span<Request> requests) {
  auto all_done = [&] {
    return std::all_of(requests.begin(), requests.end(),
                       [](const Request& request) { return request.done; });
  };
  while (!all_done()) {
    // After Stop no one leads; an upload a leader took is finished by it.
    if (log.stopped && RefuseQueued(log, requests)) break;
    if (log.leading) {
      log.changed.Wait(&log.mu);
      continue;
    }
    LeadQueued(log);
  }
}

std::vector<absl::StatusOr<Appended>> WritePath::AppendMany(
    std::string_view fleet_id,
    std::span<const std::span<const core::MemoryTrace>> uploads, bool track) {
  std::vector<absl::StatusOr<Appended>> results;
  if (uploads.empty()) return results;
  {
    absl::MutexLock lock(&ready_mu_);
    if (stopping_) {
      results.assign(uploads.size(), absl::UnavailableError(
                                         "the server is shutting down; "
                                         "nothing of this upload was stored"));
      return results;
    }
  }
  std::shared_ptr<FleetWrites> log = Find(fleet_id);
  if (log == nullptr && options_.replicated.has_value()) {
    // The owner's fleets exist (Own); this one was lost meanwhile.
    results.assign(uploads.size(),
                   absl::UnavailableError(absl::StrCat(
                       "fleet \"", V(fleet_id),
                       "\" is not owned here (ownership moved); nothing of "
                       "this upload was stored: retry")));
    return results;
  }
  if (log == nullptr) return AppendToNewFleet(fleet_id, uploads, track);

  std::vector<Request> requests(uploads.size());
  absl::MutexLock lock(&log->mu);
  for (size_t i = 0; i < uploads.size(); ++i) {
    requests[i].traces = uploads[i];
    requests[i].track = track;
    if (uploads[i].empty()) {
      requests[i].result = Appended{};
      requests[i].done = true;
    } else {
      log->queue.push_back(&requests[i]);
    }
  }
  Commit(*log, requests);
  results.reserve(requests.size());
  for (Request& request : requests) {
    results.push_back(std::move(request.result));
  }
  return results;
}

std::vector<absl::StatusOr<Appended>> WritePath::AppendToNewFleet(
    std::string_view fleet_id,
    std::span<const std::span<const core::MemoryTrace>> uploads, bool track) {
  std::vector<absl::StatusOr<Appended>> results;
  // A fleet is made by its first valid upload: checked before its log is
  // made, so that bad uploads to made-up fleets leave nothing behind.
  const auto first =
      std::find_if(uploads.begin(), uploads.end(),
                   [](std::span<const core::MemoryTrace> traces) {
                     return !traces.empty();
                   });
  if (first == uploads.end()) {
    results.assign(uploads.size(), Appended{});
    return results;
  }
  if (uploads.size() > 1) {
    // The first upload with traces alone makes the fleet (or is refused);
    // the rest follow it.
    const size_t at = static_cast<size_t>(first - uploads.begin());
    results.assign(at, Appended{});  // the empty ones before it
    results.push_back(
        std::move(AppendMany(fleet_id, uploads.subspan(at, 1), track)[0]));
    std::vector<absl::StatusOr<Appended>> rest =
        AppendMany(fleet_id, uploads.subspan(at + 1), track);
    std::move(rest.begin(), rest.end(), std::back_inserter(results));
    return results;
  }
  absl::Status valid = engine_->quota().AdmitCreationByUpload(fleet_id);
  if (valid.ok()) {
    valid = AdmitShape(engine_->quota(), fleet_id, *first, nullptr,
                       engine_->options().max_traces_per_upload);
  }
  if (valid.ok()) {
    // Nor do uploads to fleets past max_fleets (the leader admits the fleet
    // again, counting it, when it appends its first entry).
    absl::ReaderMutexLock lock(&logs_mu_);
    valid = engine_->quota().AdmitNewFleet(fleet_id, fleets_);
  }
  if (!valid.ok()) {
    results.assign(uploads.size(), valid);
    return results;
  }
  Log(fleet_id);
  return AppendMany(fleet_id, uploads, track);
}

bool WritePath::RefuseQueued(FleetWrites& log, std::span<Request> requests) {
  for (Request& request : requests) {
    if (!request.done && std::find(log.queue.begin(), log.queue.end(),
                                   &request) != log.queue.end()) {
      std::erase(log.queue, &request);
      request.result = log.closed;
      request.done = true;
    }
  }
  return std::all_of(requests.begin(), requests.end(),
                     [](const Request& request) { return request.done; });
}

void WritePath::LeadQueued(FleetWrites& log) {
  // Every upload queued so far goes into one log write.
  log.leading = true;
  std::vector<Request*> group;
  group.swap(log.queue);
  log.mu.Unlock();
  Lead(log, group);
  log.mu.Lock();
  const absl::Time now = absl::Now();
  for (Request* member : group) {
    if (member->result.ok() && member->result->sequence != 0) {
      FleetWrites::Entry entry;
      entry.sequence = member->result->sequence;
      entry.traces = member->result->accepted;
      entry.appended = now;
      if (member->track) {
        auto applied = std::make_shared<AppliedRecord>();
        entry.applied = applied;
        member->result->applied = std::move(applied);
      }
      log.backlog_traces += entry.traces;
      log.appended_through = entry.sequence;
      log.unapplied.push_back(std::move(entry));
    }
    member->done = true;
  }
  log.leading = false;
  log.changed.SignalAll();
  if (options_.on_duplicates) {
    for (const Request* member : group) {
      if (member->result.ok() && member->result->duplicates > 0) {
        options_.on_duplicates(log.id, member->result->duplicates);
      }
    }
  }
  if (!log.scheduled && !log.unapplied.empty()) {
    log.scheduled = true;
    absl::MutexLock ready(&ready_mu_);
    ready_.push_back(&log);
    ready_cv_.Signal();
  }
}

// What one group commit has admitted so far, as its leader goes through
// the group's uploads in order.
struct WritePath::Group {
  std::optional<FleetShape> shape;
  bool created = false;  // this group's first upload makes the fleet
  // A DeleteFleet is among this group's entries: what follows it makes the
  // fleet anew (no shape, no seqs received).
  bool deleted = false;
  std::string id_tag;  // FleetWrites::id_tag as this group leaves it
  // The robots' seq sets as this group leaves them; kept only if the write
  // succeeds.
  absl::flat_hash_map<std::string, core::SeqSet> seqs;
  FleetLoad load;  // backlog: the log's, and what this group adds
  std::vector<LogAppend> appends;
  std::vector<Request*> appending;  // the request of each append
};

const core::SeqSet& WritePath::SeqsOf(FleetWrites& log, Group& group,
                                      const std::string& robot_id) {
  auto [it, inserted] = group.seqs.try_emplace(robot_id);
  if (!inserted) return it->second;
  // After a DeleteFleet (this group's, or one since Open) only what was
  // admitted after it counts: the engine's received seqs are the deleted
  // fleet's until the delete is applied.
  if (group.deleted) return it->second;
  auto known = log.admitted.find(robot_id);
  if (known != log.admitted.end()) {
    it->second = known->second;
    return it->second;
  }
  if (log.remade) return it->second;
  it->second = engine_->Received(log.id, robot_id);
  auto tail = log.recovered.find(robot_id);
  if (tail != log.recovered.end()) {
    std::vector<core::SeqSet::Interval> both = it->second.Intervals();
    const std::vector<core::SeqSet::Interval> logged = tail->second.Intervals();
    both.insert(both.end(), logged.begin(), logged.end());
    it->second = core::SeqSet::FromIntervals(both);
  }
  return it->second;
}

void WritePath::AdmitCreate(FleetWrites& log, Group& group, Request& request,
                            const CreateFleetRecord& create) {
  if (group.shape.has_value()) {
    request.result = absl::AlreadyExistsError(absl::StrCat(
        "fleet \"", log.id,
        "\" exists already (made by CreateFleet or its first upload); "
        "UpdateFleet changes its settings"));
    return;
  }
  {
    absl::MutexLock lock(&logs_mu_);
    absl::Status status = engine_->quota().AdmitNewFleet(log.id, fleets_);
    if (!status.ok()) {
      request.result = status;
      return;
    }
    ++fleets_;
  }
  group.shape = FleetShape{create.code_dimension, create.encoder_version};
  group.created = true;
  request.result = Appended{};
  group.appends.push_back({*request.call});
  group.appending.push_back(&request);
}

void WritePath::Admit(FleetWrites& log, Group& group, Request& request) {
  if (request.call.has_value()) {
    if (const auto* create = std::get_if<CreateFleetRecord>(&*request.call)) {
      AdmitCreate(log, group, request, *create);
      return;
    }
    // A call needs the fleet (its first upload may still be in the log:
    // the call is applied after it); it adds no traces.
    if (!group.shape.has_value()) {
      request.result = FleetNotFound(log.id);
      return;
    }
    request.result = Appended{};
    group.appends.push_back({*request.call});
    group.appending.push_back(&request);
    if (std::holds_alternative<DeleteFleetRecord>(*request.call)) {
      group.shape.reset();
      group.seqs.clear();
      group.deleted = true;
      // The delete's own sequence (a replicated log numbers alike while
      // this owner is its only writer), as RecoverTail derives it.
      group.id_tag =
          absl::StrCat("d", log.next_sequence + group.appends.size() - 1, "/");
    }
    return;
  }
  UploadQuota& quota = engine_->quota();
  const std::span<const core::MemoryTrace> traces = request.traces;
  absl::Status status =
      AdmitShape(quota, log.id, traces, group.shape ? &*group.shape : nullptr,
                 engine_->options().max_traces_per_upload);
  const bool is_new = !group.shape.has_value();
  bool reserved = false;  // counted in fleets_ by this upload
  if (status.ok() && is_new) status = quota.AdmitCreationByUpload(log.id);
  if (status.ok() && is_new) {
    absl::MutexLock lock(&logs_mu_);
    status = quota.AdmitNewFleet(log.id, fleets_);
    if (status.ok()) {
      ++fleets_;
      reserved = true;
    }
  }
  // The receiving replica rates a replicated log's uploads (they may come
  // from any replica).
  if (status.ok() && !options_.replicated.has_value()) {
    status = quota.AdmitRates(log.id, traces);
  }
  // Duplicates: seqs admitted before, or repeated within the upload.
  absl::flat_hash_map<std::string_view, core::SeqSet> trial;
  std::vector<bool> accept(traces.size(), false);
  uint64_t accepted = 0;
  if (status.ok()) {
    for (size_t i = 0; i < traces.size(); ++i) {
      auto [it, inserted] = trial.try_emplace(traces[i].robot_id);
      if (inserted) it->second = SeqsOf(log, group, traces[i].robot_id);
      accept[i] = it->second.Insert(traces[i].seq);
      accepted += accept[i] ? 1 : 0;
    }
  }
  if (status.ok()) {
    group.load.held = engine_->HeldTraces(log.id);
    status = AdmitLoad(quota, log.id, group.load, accepted,
                       options_.max_backlog_traces);
  }
  if (!status.ok()) {
    if (reserved) {
      absl::MutexLock lock(&logs_mu_);
      fleets_ -= std::min<uint64_t>(fleets_, 1);
    }
    request.result = status;
    return;
  }
  if (is_new) {
    group.shape = FleetShape{static_cast<uint32_t>(traces[0].code.size()),
                             traces[0].encoder_version};
    group.created = true;
  }
  request.result = Appended{accepted, traces.size() - accepted, 0, nullptr};
  if (accepted > 0) Stage(group, request, accept, accepted, trial);
}

void WritePath::Stage(
    Group& group, Request& request, const std::vector<bool>& accept,
    uint64_t accepted,
    absl::flat_hash_map<std::string_view, core::SeqSet>& trial) {
  const std::span<const core::MemoryTrace> traces = request.traces;
  if (accepted == traces.size()) {
    request.accepted = traces;
  } else {
    request.kept.reserve(accepted);
    for (size_t i = 0; i < traces.size(); ++i) {
      if (accept[i]) request.kept.push_back(traces[i]);
    }
    request.accepted = request.kept;
  }
  if (options_.replicated.has_value()) {
    // A replicated log's entries: each robot's run, under its id.
    absl::StatusOr<std::vector<LogPiece>> pieces =
        options_.replicated->cut(request.accepted);
    if (!pieces.ok()) {
      request.result = pieces.status();
      return;
    }
    request.pieces = *std::move(pieces);
    for (LogPiece& piece : request.pieces) {
      if (!group.id_tag.empty()) piece.id = group.id_tag + piece.id;
      group.appends.push_back({UploadRecord{piece.traces}, piece.id});
      group.appending.push_back(&request);
    }
  } else {
    group.appends.push_back({UploadRecord{request.accepted}});
    group.appending.push_back(&request);
  }
  for (auto& [robot_id, seqs] : trial) {
    group.seqs[std::string(robot_id)] = std::move(seqs);
  }
  group.load.backlog += accepted;
}

void WritePath::Lead(FleetWrites& log, std::span<Request* const> group) {
  Group admitted;
  {
    absl::MutexLock lock(&log.mu);
    admitted.load.backlog = log.backlog_traces;
    if (!log.unapplied.empty()) {
      admitted.load.oldest_seconds =
          absl::ToDoubleSeconds(absl::Now() - log.unapplied.front().appended);
    }
  }
  admitted.shape = log.shape;
  admitted.id_tag = log.id_tag;
  for (Request* request : group) Admit(log, admitted, *request);
  if (admitted.appends.empty()) return;
  // Above the sequences this write path gave or found applied: a log that
  // lost its tail does not give them again. (A replicated log numbers its
  // own.)
  const bool replicated = options_.replicated.has_value();
  absl::StatusOr<std::vector<AppendedEntry>> written =
      log_->Append(log.id, admitted.appends,
                   {.above = replicated ? 0 : log.next_sequence - 1});
  if (!written.ok()) {
    // Every upload the group admitted fails with the write, those that
    // appended nothing too: their seqs may be duplicates of an upload
    // earlier in this group (a robot's retry queued behind its first
    // try), which is not stored now. Answered "duplicates", the robot
    // would drop traces no log holds. A replicated log may hold the first
    // entries (its status says how many): a retry under the same ids
    // stores only the rest.
    for (Request* request : group) {
      if (request->result.ok()) request->result = written.status();
    }
    if (admitted.created) {
      absl::MutexLock lock(&logs_mu_);
      fleets_ -= std::min<uint64_t>(fleets_, 1);
    }
    return;
  }
  for (size_t i = 0; i < admitted.appending.size(); ++i) {
    Appended& result = *admitted.appending[i]->result;
    result.sequence = (*written)[i].sequence;
    if ((*written)[i].duplicate) {
      // A replicated log held the entry already (a retry of an upload
      // another replica appended before this one read the log's tail).
      const auto* upload =
          std::get_if<UploadRecord>(&admitted.appends[i].record);
      const uint64_t held = upload == nullptr ? 0 : upload->traces.size();
      result.accepted -= std::min(result.accepted, held);
      result.duplicates += held;
    }
  }
  log.next_sequence = written->back().sequence + 1;
  log.shape = std::move(admitted.shape);
  if (admitted.deleted) {
    log.admitted.clear();
    log.recovered.clear();
    log.remade = true;
    log.id_tag = admitted.id_tag;
    absl::MutexLock lock(&logs_mu_);
    fleets_ -= std::min<uint64_t>(fleets_, 1);  // one made again after it in
                                                // this group counted itself
  }
  for (auto& [robot_id, seqs] : admitted.seqs) {
    log.recovered.erase(robot_id);
    log.admitted[robot_id] = std::move(seqs);
  }
}

absl::Status WritePath::WaitApplied(std::string_view fleet_id,
                                    uint64_t sequence, absl::Time deadline) {
  if (sequence == 0) return absl::OkStatus();
  std::shared_ptr<FleetWrites> log = Find(fleet_id);
  if (log == nullptr) return absl::OkStatus();
  absl::MutexLock lock(&log->mu);
  const uint64_t failures = log->apply_failures;
  while (log->applied_through < sequence) {
    // The store refuses the apply (a full disk): tell the caller now rather
    // than at its deadline; the entry is applied once writes resume.
    if (log->apply_failures > failures &&
        absl::IsResourceExhausted(log->apply_error)) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "log entry ", sequence, " of fleet \"", V(fleet_id),
          "\" is durable but cannot be applied while the store refuses "
          "writes (",
          log->apply_error.message(), "); it is applied once they resume"));
    }
    if (log->stopped) {
      return absl::UnavailableError(absl::StrCat(
          "the server is shutting down; log entry ", sequence, " of fleet \"",
          V(fleet_id),
          "\" is durable and will be applied when the server starts again"));
    }
    if (log->changed.WaitWithDeadline(&log->mu, deadline) &&
        log->applied_through < sequence) {
      return absl::DeadlineExceededError(absl::StrCat(
          "log entry ", sequence, " of fleet \"", V(fleet_id),
          "\" is durable but not applied yet (applied through ",
          log->applied_through, ", ", log->backlog_traces, " traces waiting",
          log->apply_error.ok() ? "" : ": ",
          log->apply_error.ok() ? "" : log->apply_error.ToString(), ")"));
    }
  }
  return absl::OkStatus();
}

absl::Status WritePath::WaitAppliedAll(std::string_view fleet_id,
                                       absl::Time deadline) {
  return WaitApplied(fleet_id, GetBacklog(fleet_id).appended_through, deadline);
}

Backlog WritePath::GetBacklog(std::string_view fleet_id) const {
  std::shared_ptr<FleetWrites> log = Find(fleet_id);
  Backlog backlog;
  if (log == nullptr) return backlog;
  // Damage to entries applied before the log opened lost nothing.
  for (LostLogEntries lost : log_->Losses(fleet_id)) {
    if (lost.last <= log->opened_at) continue;
    lost.first = std::max(lost.first, log->opened_at + 1);
    backlog.lost.push_back(std::move(lost));
  }
  absl::MutexLock lock(&log->mu);
  backlog.entries = log->unapplied.size();
  backlog.traces = log->backlog_traces;
  if (!log->unapplied.empty()) {
    backlog.oldest_seconds =
        absl::ToDoubleSeconds(absl::Now() - log->unapplied.front().appended);
  }
  backlog.appended_through = log->appended_through;
  backlog.applied_through = log->applied_through;
  backlog.apply_error = log->apply_error;
  return backlog;
}

size_t WritePath::QueuedUploads(std::string_view fleet_id) const {
  std::shared_ptr<FleetWrites> log = Find(fleet_id);
  if (log == nullptr) return 0;
  absl::MutexLock lock(&log->mu);
  return log->queue.size();
}

std::vector<std::pair<std::string, Backlog>> WritePath::Backlogs() const {
  std::vector<std::string> fleet_ids;
  {
    absl::ReaderMutexLock lock(&logs_mu_);
    for (const auto& [fleet_id, log] : logs_) fleet_ids.push_back(fleet_id);
  }
  std::sort(fleet_ids.begin(), fleet_ids.end());
  std::vector<std::pair<std::string, Backlog>> backlogs;
  backlogs.reserve(fleet_ids.size());
  for (std::string& fleet_id : fleet_ids) {
    Backlog backlog = GetBacklog(fleet_id);
    backlogs.emplace_back(std::move(fleet_id), std::move(backlog));
  }
  return backlogs;
}

void WritePath::Schedule(FleetWrites& log) {
  absl::MutexLock lock(&log.mu);
  if (log.scheduled || log.unapplied.empty()) return;
  log.scheduled = true;
  absl::MutexLock ready(&ready_mu_);
  ready_.push_back(&log);
  ready_cv_.Signal();
}

void WritePath::RunApplier() {
  if (absl::Status marked =
          common::MarkBackgroundThread("fleetmem-apply", options_.applier_nice);
      !marked.ok()) {
    FLEETMEM_LOG(kWarning) << "applier thread: " << marked;
  }
  while (true) {
    FleetWrites* log = nullptr;
    {
      absl::MutexLock lock(&ready_mu_);
      while (!stopping_ && ready_.empty()) ready_cv_.Wait(&ready_mu_);
      if (stopping_) return;
      log = ready_.front();
      ready_.pop_front();
    }
    ApplyTurn(*log);
    absl::MutexLock lock(&log->mu);
    // Entries appended during the turn found the fleet scheduled: its turn
    // comes again for them too.
    if (!log->unapplied.empty()) {
      // Round robin: the fleet goes to the back of the queue.
      absl::MutexLock ready(&ready_mu_);
      ready_.push_back(log);
      ready_cv_.Signal();
    } else {
      log->scheduled = false;
    }
  }
}

void WritePath::ApplyTurn(FleetWrites& log) {
  uint64_t from = 0;
  uint64_t through = 0;
  {
    absl::MutexLock lock(&log.mu);
    from = log.applied_through;
    through = log.appended_through;
  }
  if (through <= from) return;
  ApplyHooks hooks;
  hooks.may_apply = [&](const LogEntry& entry) {
    return entry.sequence <= through && !stop_.load(std::memory_order_relaxed);
  };
  hooks.applied = [&](const LogEntry& entry, const AppliedRecord& applied) {
    if (applied.duplicates > 0) {
      // Append admits only seqs the fleet has not received: a duplicate
      // here is an entry applied twice (the crash trials count this line).
      FLEETMEM_LOG(kError) << "fleet \"" << log.id
                           << "\": " << applied.duplicates
                           << " traces of log entry " << entry.sequence
                           << " were applied twice";
    }
    MarkApplied(log, entry.sequence, applied);
  };
  absl::StatusOr<AppliedTurn> turn =
      applier_.Turn(log.id, from, options_.apply_batch, hooks);
  if (!turn.ok()) return WaitToRetry(log, from, turn.status());
  if (turn->applied == 0 && turn->stopped.ok() &&
      !stop_.load(std::memory_order_relaxed)) {
    // The log holds no entry from `from` through `through`.
    if (LostFrom(log_->Losses(log.id), from) >= through) {
      // Every entry left was found damaged (reported as it was found).
      MarkApplied(log, through, AppliedRecord{});
      return;
    }
    return WaitToRetry(
        log, from,
        absl::DataLossError(absl::StrCat("the log holds no entry after ", from,
                                         " though entries through ", through,
                                         " were acknowledged")));
  }
  if (turn->position > from) {
    if (absl::Status trimmed = log_->Trim(log.id, turn->position);
        !trimmed.ok()) {
      FLEETMEM_LOG(kWarning)
          << "fleet \"" << log.id << "\": applied log entries through "
          << turn->position
          << " not trimmed (the next turn or Open does): " << trimmed;
    }
  }
  // The store refused (a full disk): retried until it applies; never
  // dropped. (No limit refuses an acknowledged entry: engine/admission.h.)
  if (!turn->stopped.ok()) WaitToRetry(log, turn->position, turn->stopped);
}

void WritePath::MarkApplied(FleetWrites& log, uint64_t sequence,
                            const AppliedRecord& outcome) {
  absl::MutexLock lock(&log.mu);
  while (!log.unapplied.empty() && log.unapplied.front().sequence <= sequence) {
    FleetWrites::Entry& done = log.unapplied.front();
    log.backlog_traces -= std::min(log.backlog_traces, done.traces);
    if (done.applied != nullptr && done.sequence == sequence) {
      *done.applied = outcome;
    }
    log.unapplied.pop_front();
  }
  log.applied_through = sequence;
  log.apply_error = absl::OkStatus();
  log.changed.SignalAll();
}

void WritePath::WaitToRetry(FleetWrites& log, uint64_t from,
                            const absl::Status& status) {
  FLEETMEM_LOG(kError) << "fleet \"" << log.id
                       << "\": applying the log after entry " << from
                       << " failed (retried in " << options_.retry_interval
                       << "): " << status;
  {
    absl::MutexLock lock(&log.mu);
    log.apply_error = status;
    ++log.apply_failures;
    log.changed.SignalAll();
  }
  absl::MutexLock lock(&ready_mu_);
  if (!stopping_) stop_cv_.WaitWithTimeout(&ready_mu_, options_.retry_interval);
}

bool WritePath::Drain(absl::Time deadline) {
  bool drained = true;
  for (const auto& [fleet_id, backlog] : Backlogs()) {
    if (backlog.entries == 0) continue;
    const absl::Status waited =
        WaitApplied(fleet_id, backlog.appended_through, deadline);
    if (!waited.ok()) {
      FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id
                             << "\": log not applied before shutdown, the "
                                "next start applies the rest: "
                             << waited;
      drained = false;
    }
  }
  return drained;
}

void WritePath::Stop() {
  {
    absl::MutexLock lock(&ready_mu_);
    if (stopping_ && appliers_.empty()) return;
    stopping_ = true;
    stop_.store(true, std::memory_order_relaxed);
    ready_cv_.SignalAll();
    stop_cv_.SignalAll();
  }
  std::vector<FleetWrites*> logs;
  {
    absl::ReaderMutexLock lock(&logs_mu_);
    for (auto& [fleet_id, log] : logs_) logs.push_back(log.get());
  }
  for (FleetWrites* log : logs) {
    absl::MutexLock lock(&log->mu);
    log->stopped = true;
    log->closed = absl::UnavailableError(
        "the server is shutting down; nothing of this upload was stored");
    log->changed.SignalAll();
  }
  for (std::thread& applier : appliers_) applier.join();
  appliers_.clear();
}

}  // namespace fleetmem::engine
