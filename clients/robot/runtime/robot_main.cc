// fleetmem-robot: one robot of a fleet, as its own program (docs/robot.md).
// It observes a recorded source (Nordland images, images with poses, a
// CARMEN laser log), relocalises each observation against the fleet's
// memory, queues its memory traces on its own disk and uploads them whenever
// the server answers, and keeps its dynamic memory refreshed from the whole
// fleet. Restarted on the same --data-dir it resumes where it stopped: no
// observation is made twice or skipped, no seq is reused.
//
//   fleetmem-robot --server 127.0.0.1:50051 --fleet nordland
//       --robot-id robot-1 --source nordland:../shared/data/nordland/summer
//       --data-dir /var/lib/fleetmem-robot --first 0 --last 300
//
// With --slam (a laser source) it maps: keyframes by travel, loop closure
// through the fleet's memory, a pose graph; trajectory.tum, map.png and
// slam.json in --data-dir (clients/robot/slam/fleet_slam.h, docs/slam.md).
//
// Exit codes: 0 the source was observed and the queue drained, or SIGTERM /
// SIGINT stopped it cleanly; 1 an error (the message says what was kept);
// 2 bad flags; 3 the source was observed but the queue did not drain within
// --drain-timeout (it is kept for the next start).
#include <algorithm>
#include <csignal>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <optional>
#include <string>
#include <utility>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/learning/gpl_robot.h"
#include "clients/robot/learning/metric_robot.h"
#include "clients/robot/memory/robot_store.h"
#include "clients/robot/runtime/agent.h"
#include "clients/robot/runtime/migration.h"
#include "clients/robot/sensing/encoder_factory.h"
#include "clients/robot/sensing/observation_source.h"
#include "clients/robot/slam/fleet_slam.h"
#include "clients/robot/vo/vo_deployment.h"
#include "fleetmem_version.h"
#include "services/common/cli_program.h"
#include "services/core/validation.h"

namespace {

std::atomic<bool> g_stop{false};

extern "C" void OnSignal(int) { g_stop.store(true); }

struct Flags {
  std::string server = "127.0.0.1:50051";
  std::string fleet;
  std::string robot_id;
  std::string source;
  std::string data_dir;
  fleetmem::client::CredentialSources credentials;
  std::string tls_server_name;
  std::string encoder;
  std::string gpl_model;
  bool learn = false;
  bool rescore = false;
  std::string rewards = "full";
  std::string migrate_from;
  int learn_steps = 60;
  int torch_threads = 2;
  std::string domain;
  size_t segment_size = 200;
  double rate_hz = 0.0;
  size_t first = 0;
  size_t last = 0;  // 0 = to the end
  bool query_only = false;
  bool no_relocalise = false;
  bool score_odometry = false;
  double match_radius = 0.0;  // 0 = the source's default
  uint32_t query_k = 6;
  size_t sequence = 10;
  uint32_t sequence_candidates = 20;
  size_t dynamic_memory = 1000;
  double gamma = 0.9;
  uint32_t refresh_count = 0;
  bool no_warm_start = false;
  size_t replay_per_segment = 64;
  size_t recall_per_observation = 4;
  size_t upload_batch = 200;
  double queue_max_mb = 256.0;
  double disk_reserve_mb = 64.0;
  std::string queue_full_policy = "refuse";
  double drain_timeout_s = 120.0;
  double first_contact_timeout_s = 60.0;
  double deadline_s = 10.0;
  uint64_t seed = 1;
  bool slam = false;
  double keyframe_distance_m = 0.5;
  bool vo = false;
  std::string vo_model;
  std::string vo_method = "cl_slam";
  std::string vo_environment;
  int vo_update_steps = 5;
};

// Long (170 lines) by its nature: one CLI11 declaration per flag, in the
// order --help prints them; cut, it would only scatter that list.
void AddFlags(CLI::App& app, Flags& flags) {
  app.add_option("--server", flags.server, "fleetmem-server HOST:PORT")
      ->capture_default_str();
  app.add_option("--fleet", flags.fleet, "fleet id")->required();
  app.add_option("--robot-id", flags.robot_id,
                 "this robot's id (stable across restarts)")
      ->required();
  app.add_option("--source", flags.source,
                 "nordland:DIR | images:DIR,POSES.csv | carmen:FILE[.bz2] | "
                 "kitti:DIR (with --vo)")
      ->required();
  app.add_option("--data-dir", flags.data_dir,
                 "the robot's own durable state: upload queue, source "
                 "position, seq counter, watch cursor, status.json")
      ->required();
  app.add_option("--token-file", flags.credentials.token_file,
                 "file with the token NAME:SECRET (or FLEETMEM_TOKEN_FILE / "
                 "FLEETMEM_TOKEN)");
  app.add_option("--tls-ca", flags.credentials.ca_file,
                 "PEM of the server's CA: turns TLS on");
  app.add_option("--tls-cert", flags.credentials.cert_file,
                 "client certificate (PEM) for mutual TLS");
  app.add_option("--tls-key", flags.credentials.key_file,
                 "client private key (PEM) for mutual TLS");
  app.add_option("--tls-server-name", flags.tls_server_name,
                 "name to expect in the server's certificate");
  app.add_option("--encoder", flags.encoder,
                 "place code (default: hog-64x32-c8-s8-b6 for images, "
                 "scanring-r32-d32 for scans)");
  app.add_option("--gpl-model", flags.gpl_model,
                 "GPL model file (fleetmem-eval pretrain): its frozen encoder "
                 "makes the codes (instead of --encoder)");
  app.add_flag("--learn", flags.learn,
               "learn a place head every segment from the segment and the "
               "traces replayed from the dynamic memory: a metric head on "
               "the --encoder code (kept in DATA_DIR/metric-head.bin), or "
               "with --gpl-model the GPL place head (DATA_DIR/gpl-learned.pt)");
  app.add_flag("--rescore", flags.rescore,
               "with --learn: after each segment, re-score the robot's own "
               "remembered traces under the new head and send their R_ex to "
               "the fleet (UpdateRewards), so refreshes draw with it");
  app.add_option("--rewards", flags.rewards,
                 "the R of each trace: full (R_ex + R_in, Eq. 13) or flat "
                 "(R = 1: with --gamma 1 and a fleet made with --refresh-pairs "
                 "and --replay-decay 1, the memory rule that measured best "
                 "for the learned head; docs/results.md)")
      ->capture_default_str()
      ->check(CLI::IsMember({"full", "flat"}));
  app.add_option("--migrate-from", flags.migrate_from,
                 "encoder migration: DATA_DIR belongs to this fleet (or "
                 "alias); before observing, re-encode with --encoder what it "
                 "still holds of this robot's traces and upload them to "
                 "--fleet under the same seqs, then move DATA_DIR to --fleet "
                 "(resumable; nothing to do once moved; docs/robot.md)");
  app.add_option("--learn-steps", flags.learn_steps,
                 "GPL place-head gradient steps per segment (--gpl-model)")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  app.add_option("--torch-threads", flags.torch_threads,
                 "intra-op threads of the learned models (--gpl-model, --vo)")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  app.add_option("--domain", flags.domain,
                 "domain of the traces (default: the Nordland folder's name, "
                 "\"images\" or \"lidar\")");
  app.add_option("--segment-size", flags.segment_size,
                 "observations per segment (Algorithm 3)")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--rate", flags.rate_hz,
                 "observations per second, 0 = as fast as possible")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  app.add_option("--first", flags.first, "first source index to observe")
      ->capture_default_str();
  app.add_option("--last", flags.last,
                 "stop before this source index (0 = the end)")
      ->capture_default_str();
  app.add_flag("--query-only", flags.query_only,
               "relocalise only: upload nothing (e.g. a winter drive "
               "querying the summer memory)");
  app.add_flag("--no-relocalise", flags.no_relocalise,
               "do not query the fleet per observation");
  app.add_flag("--score-odometry", flags.score_odometry,
               "score relocalisations against a laser log's odometry poses "
               "(not ground truth: they drift)");
  app.add_option("--match-radius", flags.match_radius,
                 "a relocalisation within this distance is correct (place "
                 "units; 0 = the source's default: 20 for Nordland, 2 m "
                 "otherwise)")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--query-k", flags.query_k, "matches per relocalisation")
      ->capture_default_str()
      ->check(CLI::Range(1, 100));
  app.add_option("--sequence", flags.sequence,
                 "also relocalise over the last N frames (re-ranks each "
                 "answer, scored apart; 1 = single frames only; docs/robot.md)")
      ->capture_default_str()
      ->check(CLI::Range(1, 100));
  app.add_option("--sequence-candidates", flags.sequence_candidates,
                 "matches asked per frame when --sequence is above 1")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000));
  app.add_option("--dynamic-memory", flags.dynamic_memory,
                 "capacity of the dynamic memory M_D")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--gamma", flags.gamma, "time decay of replay (Eq. 19)")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1.0));
  app.add_flag("--no-warm-start", flags.no_warm_start,
               "with --learn: do not fit the learner on the first refresh "
               "before a new robot's first frame");
  app.add_option("--refresh-count", flags.refresh_count,
                 "traces per refresh (0 = the capacity of M_D)")
      ->capture_default_str();
  app.add_option("--replay-per-segment", flags.replay_per_segment,
                 "traces replayed from M_D per segment")
      ->capture_default_str();
  app.add_option("--recall-per-observation", flags.recall_per_observation,
                 "fleet traces recalled per new observation at the end of a "
                 "segment (QueryPlace near its place), the learner's partners "
                 "(0 = none; at most the server's max_query_k, 1000 by "
                 "default)")
      ->capture_default_str()
      ->check(CLI::Range(size_t{0}, size_t{1000}));
  app.add_option("--upload-batch", flags.upload_batch, "traces per upload")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--queue-max-mb", flags.queue_max_mb,
                 "bound of the upload queue (MiB)")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--disk-reserve-mb", flags.disk_reserve_mb,
                 "refuse to record while the data dir's filesystem has less "
                 "free (MiB)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  app.add_option("--queue-full-policy", flags.queue_full_policy,
                 "refuse (stop observing until it drains) or drop-oldest")
      ->capture_default_str()
      ->check(CLI::IsMember({"refuse", "drop-oldest"}));
  app.add_option("--drain-timeout", flags.drain_timeout_s,
                 "seconds to wait for the queue to drain at the end")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  app.add_option("--first-contact-timeout", flags.first_contact_timeout_s,
                 "seconds a first start on an empty data dir waits for an "
                 "unreachable server before it gives up")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  app.add_option("--deadline", flags.deadline_s, "seconds per server call")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_flag("--slam", flags.slam,
               "map a laser source: observe keyframes, close loops through "
               "the fleet, write trajectory.tum, map.png, slam.json to "
               "--data-dir (--first/--last count keyframes; the segment "
               "size defaults to 25)");
  app.add_option("--keyframe-distance", flags.keyframe_distance_m,
                 "with --slam: metres of travel between keyframes")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_flag("--vo", flags.vo,
               "continual visual odometry (CL-SLAM) on a kitti:DIR source: "
               "one deployment adapting online, the trajectory in KITTI and "
               "TUM format under DATA_DIR/vo/, the weights for the next "
               "deployment in DATA_DIR/vo-weights.pt; runs on the robot "
               "alone (no server call)");
  app.add_option("--vo-model", flags.vo_model,
                 "with --vo: the fleet's pre-trained weights, used while "
                 "DATA_DIR/vo-weights.pt does not exist");
  app.add_option("--vo-method", flags.vo_method,
                 "with --vo: cl_slam | expert_only | generalizer_only | fixed")
      ->capture_default_str();
  app.add_option("--vo-environment", flags.vo_environment,
                 "with --vo: the environment's name (replay buffer; default "
                 "the sequence folder's name)");
  app.add_option("--vo-update-steps", flags.vo_update_steps,
                 "with --vo: c, update steps per new frame")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  app.add_option("--seed", flags.seed, "seed of R_in and replay draws")
      ->capture_default_str();
  app.set_config("--config", "",
                 "TOML or INI file of these options (flags win)");
  // CLI11 ignores unknown keys of a config file by default: a misspelt
  // option would silently keep its default. Refuse them.
  app.allow_config_extras(CLI::config_extras_mode::error);
}

// The robot's GPL model: its own learned copy (DATA_DIR/gpl-learned.pt,
// written after every segment) when it learns and has one of the same
// encoder version, else the fleet's model file.
absl::StatusOr<std::unique_ptr<fleetmem::robot::gpl::SharedModel>> LoadGplModel(
    const std::string& fleet_model, const std::string& learned, bool learn) {
  namespace gpl = fleetmem::robot::gpl;
  absl::StatusOr<std::unique_ptr<gpl::SharedModel>> model =
      gpl::LoadSharedModel(fleet_model);
  if (!model.ok() || !learn || !std::filesystem::exists(learned)) return model;
  absl::StatusOr<std::unique_ptr<gpl::SharedModel>> own =
      gpl::LoadSharedModel(learned);
  if (!own.ok()) {
    return absl::Status(
        own.status().code(),
        absl::StrCat("the robot's learned model: ", own.status().message()));
  }
  absl::MutexLock a(&(*model)->mu);
  absl::MutexLock b(&(*own)->mu);
  if ((*own)->model->version() != (*model)->model->version()) {
    return absl::FailedPreconditionError(
        absl::StrCat(learned, " holds encoder ", (*own)->model->version(),
                     " but --gpl-model is ", (*model)->model->version(),
                     ": a new fleet encoder needs a new data dir"));
  }
  return own;
}

// The highest seq the fleet holds of this robot (0 if none, or if the fleet
// does not exist yet). A robot that has not given a seq yet starts after it,
// so that a robot whose disk was wiped does not reuse them. A server that
// cannot be reached (it may be restarting) is asked again, with backoff, for
// up to --first-contact-timeout seconds; any other error ends at once.
absl::StatusOr<uint64_t> ServerMaxSeq(fleetmem::client::Client& client,
                                      const Flags& flags) {
  const absl::Time give_up =
      absl::Now() + absl::Seconds(flags.first_contact_timeout_s);
  absl::Duration backoff = absl::Milliseconds(200);
  absl::StatusOr<fleetmem::v1::GetStatsResponse> stats =
      client.GetStats(flags.fleet);
  while (!stats.ok() && fleetmem::robot::IsRetryable(stats.status().code()) &&
         absl::Now() + backoff < give_up) {
    std::cerr << "[" << flags.robot_id << "] waiting for the server before a "
              << "first start (" << stats.status().message() << ")\n";
    absl::SleepFor(backoff);
    backoff = std::min(backoff * 2, absl::Seconds(5));
    stats = client.GetStats(flags.fleet);
  }
  if (!stats.ok() && stats.status().code() == absl::StatusCode::kNotFound) {
    return 0;  // a new fleet
  }
  if (!stats.ok()) {
    return absl::Status(
        stats.status().code(),
        absl::StrCat("a robot's first start must reach the server to learn "
                     "its last seq (nothing was observed or written): ",
                     stats.status().message()));
  }
  for (const fleetmem::v1::RobotStats& robot : stats->robots()) {
    if (robot.robot_id() == flags.robot_id) return robot.max_seq();
  }
  return 0;
}

// True if the store has given no seq and holds nothing.
bool GaveNoSeq(const fleetmem::robot::RobotStore& store) {
  const fleetmem::robot::RobotState state = store.state();
  return state.next_seq() == 1 && state.traces_queued() == 0 &&
         store.queue().open_segment == 0;
}

// fleetmem-robot --vo: one deployment of the continual visual odometry
// (clients/robot/vo/vo_deployment.h).
int RunVo(const Flags& flags) {
  namespace vo = fleetmem::vo;
  if (!flags.source.starts_with("kitti:")) {
    std::cerr << "fleetmem-robot: --vo needs --source kitti:DIR (image_l/, "
                 "calib.txt, optional poses.txt)\n";
    return 2;
  }
  absl::StatusOr<vo::VoMethod> method = vo::ParseVoMethod(flags.vo_method);
  if (!method.ok()) {
    std::cerr << "fleetmem-robot: " << method.status().message() << "\n";
    return 2;
  }
  vo::VoDeploymentOptions options;
  options.sequence_dir = flags.source.substr(6);
  options.data_dir = flags.data_dir;
  options.initial_model = flags.vo_model;
  options.environment = flags.vo_environment;
  options.method = *method;
  options.vo.update_steps = flags.vo_update_steps;
  options.vo.seed = flags.seed;
  fleetmem::robot::gpl::SetTorchThreads(flags.torch_threads);
  absl::StatusOr<vo::VoDeploymentReport> report =
      vo::RunVoDeployment(options, [](size_t frame, size_t frames) {
        if (frame % 10 == 0 || frame + 1 == frames) {
          std::cerr << "vo: frame " << frame + 1 << "/" << frames << "\n";
        }
      });
  if (!report.ok()) {
    std::cerr << "fleetmem-robot: " << report.status().ToString() << "\n";
    return 1;
  }
  std::cout << "vo: " << report->result.odometry.size() << " frames, "
            << report->result.adapted_frames << " adapted, "
            << report->result.loops << " loops, "
            << absl::StrFormat("%.1f s", report->result.seconds);
  if (report->ate_se3_m >= 0.0) {
    std::cout << absl::StrFormat(", ATE %.3f m", report->ate_se3_m);
  }
  std::cout << "; trajectory in " << report->out_dir << "\n";
  return 0;
}

// Run's steps fail with the process's exit code (2: a flag or file the
// user must fix; 1: the run failed) and what it prints.
struct Failure {
  int exit_code = 1;
  std::string message;
};
using Failed = std::optional<Failure>;

Failed Fail(int exit_code, const absl::Status& status) {
  return Failure{exit_code, std::string(status.message())};
}

// The flags that cannot go together, and the ids.
Failed CheckFlags(const Flags& flags) {
  for (const auto& [what, id] : {std::pair{"--fleet", &flags.fleet},
                                 std::pair{"--robot-id", &flags.robot_id}}) {
    absl::Status valid = fleetmem::core::ValidateId(what, *id);
    if (!valid.ok()) return Fail(2, valid);
  }
  if (flags.slam && flags.query_only) {
    return Failure{2,
                   "--slam maps and uploads its keyframes; it cannot be "
                   "--query-only"};
  }
  if (!flags.gpl_model.empty() && !flags.encoder.empty()) {
    return Failure{2, "give --encoder or --gpl-model, not both"};
  }
  if (!flags.migrate_from.empty()) {
    absl::Status valid =
        fleetmem::core::ValidateId("--migrate-from", flags.migrate_from);
    if (!valid.ok()) return Fail(2, valid);
    if (flags.migrate_from == flags.fleet || flags.query_only) {
      return Failure{2,
                     "--migrate-from names the fleet an uploading robot's "
                     "DATA_DIR belongs to now, another than --fleet"};
    }
  }
  if (flags.rescore && (!flags.learn || flags.query_only)) {
    return Failure{2,
                   "--rescore re-scores with the head --learn trains, the "
                   "robot's own uploaded traces: it needs --learn and an "
                   "uploading robot"};
  }
  return std::nullopt;
}

// What the robot senses with: its source (under the SLAM front end's
// keyframes with --slam), its encoder and the GPL model behind it.
struct Sensing {
  std::unique_ptr<fleetmem::robot::ObservationSource> source;
  const fleetmem::slam::KeyframeSource* keyframes = nullptr;  // --slam
  std::unique_ptr<fleetmem::robot::gpl::SharedModel> gpl;     // --gpl-model
  std::unique_ptr<fleetmem::robot::Encoder> encoder;
};

Failed OpenSensing(const Flags& flags,
                   const fleetmem::slam::LaserSlamOptions& slam_options,
                   Sensing& sensing) {
  namespace robot = fleetmem::robot;
  absl::StatusOr<std::unique_ptr<robot::ObservationSource>> source =
      robot::OpenSource(flags.source);
  if (!source.ok()) return Fail(1, source.status());
  sensing.source = *std::move(source);
  if (flags.slam) {
    absl::StatusOr<std::unique_ptr<fleetmem::slam::KeyframeSource>> k =
        fleetmem::slam::KeyframeSource::Open(std::move(sensing.source),
                                             slam_options);
    if (!k.ok()) return Fail(2, k.status());
    sensing.keyframes = k->get();
    sensing.source = *std::move(k);
  }
  absl::StatusOr<std::unique_ptr<robot::Encoder>> encoder;
  if (!flags.gpl_model.empty()) {
    robot::gpl::SetTorchThreads(flags.torch_threads);
    absl::StatusOr<std::unique_ptr<robot::gpl::SharedModel>> model =
        LoadGplModel(flags.gpl_model, flags.data_dir + "/gpl-learned.pt",
                     flags.learn);
    if (!model.ok()) return Fail(2, model.status());
    sensing.gpl = *std::move(model);
    encoder = std::unique_ptr<robot::Encoder>(
        new robot::gpl::GplEncoder(sensing.gpl.get()));
  } else {
    encoder = robot::NewEncoderByName(flags.encoder.empty()
                                          ? sensing.source->default_encoder()
                                          : flags.encoder);
  }
  if (!encoder.ok()) return Fail(2, encoder.status());
  sensing.encoder = *std::move(encoder);
  return std::nullopt;
}

// The robot's connections: a retrying one for the first-start check, the
// agent's (one attempt per call: the uploader and watcher retry on their
// own), a query client with a short deadline, and the options of the
// uploader's own channel (reopened after failures, agent.h).
struct Clients {
  std::unique_ptr<fleetmem::client::Client> setup;
  std::unique_ptr<fleetmem::client::Client> agent;
  std::unique_ptr<fleetmem::client::Client> query;
  fleetmem::client::ClientOptions upload;
};

Failed Connect(const Flags& flags, Clients& clients) {
  namespace client = fleetmem::client;
  client::ClientOptions options;
  options.target = flags.server;
  options.deadline =
      std::chrono::milliseconds(static_cast<int64_t>(flags.deadline_s * 1000));
  options.tls_server_name = flags.tls_server_name;
  absl::Status loaded = client::LoadCredentials(flags.credentials, &options);
  if (!loaded.ok()) return Fail(2, loaded);
  clients.setup = client::Client::Create(options);
  options.max_attempts = 1;
  options.upload_batch_size = flags.upload_batch;
  // Answered at the durable append: the robot's queue is freed as soon as
  // the server holds its traces; replay (SampleReplay) waits on the server
  // for them to be applied.
  options.upload_ack = fleetmem::v1::UPLOAD_ACK_DURABLE;
  clients.agent = client::Client::Create(options);
  clients.upload = options;
  options.deadline =
      std::min(options.deadline, std::chrono::milliseconds(2000));
  clients.query = client::Client::Create(options);
  return std::nullopt;
}

// The robot's store in its data dir, as the robot of `fleet_id`.
absl::StatusOr<std::unique_ptr<fleetmem::robot::RobotStore>> OpenStore(
    const Flags& flags, const Sensing& sensing, const std::string& fleet_id) {
  namespace robot = fleetmem::robot;
  robot::RobotStoreOptions store_options;
  store_options.max_bytes =
      static_cast<uint64_t>(flags.queue_max_mb * 1024.0 * 1024.0);
  store_options.full_policy = *robot::ParseFullPolicy(flags.queue_full_policy);
  store_options.min_free_bytes =
      static_cast<uint64_t>(flags.disk_reserve_mb * 1024.0 * 1024.0);
  return robot::RobotStore::Open(flags.data_dir,
                                 {.robot_id = flags.robot_id,
                                  .fleet_id = fleet_id,
                                  .source = sensing.source->description()},
                                 store_options);
}

// The robot's store-and-forward queue in its data dir. A first start asks
// the server for the robot's last seq before anything is written here, and
// continues after it.
Failed OpenQueue(const Flags& flags, const Sensing& sensing,
                 fleetmem::client::Client& setup,
                 std::unique_ptr<fleetmem::robot::RobotStore>& queue) {
  namespace robot = fleetmem::robot;
  const bool new_dir =
      !std::filesystem::exists(std::filesystem::path(flags.data_dir) / "queue");
  std::optional<absl::StatusOr<uint64_t>> max_seq;
  if (!flags.query_only && new_dir) {
    max_seq = ServerMaxSeq(setup, flags);
    if (!max_seq->ok()) return Fail(1, max_seq->status());
  }
  absl::StatusOr<std::unique_ptr<robot::RobotStore>> store =
      OpenStore(flags, sensing, flags.fleet);
  if (!store.ok()) return Fail(1, store.status());
  queue = *std::move(store);
  if (flags.query_only || !GaveNoSeq(*queue)) return std::nullopt;
  if (!max_seq.has_value()) max_seq = ServerMaxSeq(setup, flags);
  absl::Status first = max_seq->status();
  if (first.ok() && **max_seq > 0) {
    std::cerr << "[" << flags.robot_id << "] the fleet already holds seqs "
              << "up to " << **max_seq << " of this robot; continuing after "
              << "them\n";
    first = queue->SetFirstSeq(**max_seq + 1);
  }
  if (!first.ok()) return Fail(1, first);
  return std::nullopt;
}

// --migrate-from: the data dir of the old fleet moved to --fleet with its
// traces re-encoded (migration.h), or found moved already. The learned
// heads were fitted to the old codes: kept aside under the old fleet's
// name, and the robot learns anew.
Failed Migrate(const Flags& flags, const Sensing& sensing,
               fleetmem::client::Client& setup) {
  namespace robot = fleetmem::robot;
  if (!std::filesystem::exists(std::filesystem::path(flags.data_dir) /
                               "queue")) {
    return Failure{
        2, absl::StrCat("--migrate-from ", flags.migrate_from, ": ",
                        flags.data_dir, " holds no robot state to migrate")};
  }
  absl::StatusOr<std::unique_ptr<robot::RobotStore>> store =
      OpenStore(flags, sensing, flags.migrate_from);
  if (absl::IsFailedPrecondition(store.status())) {
    // Moved to --fleet already (nothing left to do), or another fleet's:
    // --migrate-from names the fleet (or alias) the robot ran with.
    if (OpenStore(flags, sensing, flags.fleet).ok()) return std::nullopt;
    return Failure{2, absl::StrCat("--migrate-from ", flags.migrate_from, ": ",
                                   store.status().message())};
  }
  if (!store.ok()) return Fail(1, store.status());
  robot::MigrationOptions options;
  options.from_fleet = flags.migrate_from;
  options.to_fleet = flags.fleet;
  options.seed = flags.seed;
  options.log = [&flags](std::string_view line) {
    std::cerr << "[" << flags.robot_id << "] " << line << "\n";
  };
  absl::StatusOr<robot::MigrationSummary> done = robot::MigrateRobot(
      options, setup, *sensing.source, *sensing.encoder, **store);
  if (!done.ok()) return Fail(1, done.status());
  for (const char* head : {"metric-head.bin", "gpl-learned.pt"}) {
    const std::filesystem::path path =
        std::filesystem::path(flags.data_dir) / head;
    std::error_code error;
    if (!std::filesystem::exists(path, error)) continue;
    std::filesystem::rename(
        path, path.string() + "." + flags.migrate_from + ".old", error);
    if (error)
      return Failure{1, absl::StrCat("cannot set ", path.string(),
                                     " aside: ", error.message())};
  }
  std::cerr << absl::StrFormat(
      "[%s] migrated to fleet %s: %d traces re-encoded and acknowledged "
      "(%d held there already), %d no longer held by %s, %d sealed before "
      "source positions were kept (left in %s); the data dir now belongs to "
      "%s\n",
      flags.robot_id, flags.fleet, done->migrated, done->duplicates,
      done->not_held, flags.migrate_from, done->no_source, flags.migrate_from,
      flags.fleet);
  return std::nullopt;  // OpenQueue opens the data dir as --fleet's
}

fleetmem::robot::AgentOptions MakeAgentOptions(const Flags& flags,
                                               const Sensing& sensing) {
  fleetmem::robot::AgentOptions options;
  options.fleet_id = flags.fleet;
  options.robot_id = flags.robot_id;
  options.domain =
      flags.domain.empty() ? sensing.source->default_domain() : flags.domain;
  options.segment_size = flags.segment_size;
  options.first = flags.first;
  if (flags.last > 0) options.last = flags.last;
  options.rate_hz = flags.rate_hz;
  options.upload = !flags.query_only;
  // With --slam the SLAM back end asks the fleet itself (own traces near its
  // estimate, peers' by code).
  options.relocalise = !flags.no_relocalise && !flags.slam;
  options.query_k = flags.query_k;
  options.score_relocalisation =
      sensing.source->places_are_ground_truth() || flags.score_odometry;
  options.match_radius = flags.match_radius > 0.0
                             ? flags.match_radius
                             : sensing.source->default_match_radius();
  options.sequence.length = flags.sequence;
  options.sequence.tolerance = options.match_radius;
  options.sequence_candidates = flags.sequence_candidates;
  // Triplet radii scale with the match radius: Nordland's 20 units give the
  // demo's positives within 10 (adjacent files) and negatives beyond 100.
  options.step.triplet.positive_radius = options.match_radius / 2.0;
  options.step.triplet.negative_radius = options.match_radius * 5.0;
  options.dynamic_memory.capacity = flags.dynamic_memory;
  options.dynamic_memory.gamma = flags.gamma;
  options.refresh_count = flags.refresh_count;
  options.warm_start = !flags.no_warm_start;
  options.step.replay_per_segment = flags.replay_per_segment;
  options.step.recall_per_observation = flags.recall_per_observation;
  options.step.rescore_remembered = flags.rescore;
  options.step.rewards = flags.rewards == "flat"
                             ? fleetmem::robot::RewardMode::kUniform
                             : fleetmem::robot::RewardMode::kFull;
  options.upload_batch = flags.upload_batch;
  options.drain_timeout = std::chrono::milliseconds(
      static_cast<int64_t>(flags.drain_timeout_s * 1000));
  options.status_file = flags.data_dir + "/status.json";
  options.seed = flags.seed;
  return options;
}

// With --learn: the metric head on the fleet code (docs/results.md: the
// better of the two learners on the lifelong protocol), or, with a GPL
// model, the GPL learner. Null without --learn.
Failed MakeLearner(const Flags& flags,
                   const fleetmem::robot::AgentOptions& options,
                   const Sensing& sensing,
                   std::unique_ptr<fleetmem::robot::Learner>& learner) {
  namespace gpl = fleetmem::robot::gpl;
  if (!flags.learn) return std::nullopt;
  if (sensing.gpl == nullptr) {
    // Pairs within the match radius, R_ex's negatives beyond the triplet
    // radius, as the GPL learner's.
    gpl::MetricHeadOptions head;
    head.pair_radius = options.match_radius;
    head.mining.positive_radius = options.match_radius;
    head.mining.negative_radius = options.step.triplet.negative_radius;
    const std::string path = flags.data_dir + "/metric-head.bin";
    absl::StatusOr<gpl::MetricHead> loaded = gpl::MetricRobotLearner::LoadOrNew(
        path, int(sensing.encoder->dimension()), head);
    if (!loaded.ok()) {
      return Failure{2, absl::StrCat("the robot's learned head: ",
                                     loaded.status().message())};
    }
    learner =
        std::make_unique<gpl::MetricRobotLearner>(*std::move(loaded), path);
    return std::nullopt;
  }
  gpl::SegmentLearnerOptions learn;
  learn.steps_per_segment = flags.learn_steps;
  learn.seed = flags.seed;
  // Positives within the match radius (a correct match), negatives beyond
  // five of it (as the code-space R_ex, rewards.h).
  learn.mining.positive_radius = options.match_radius;
  learn.mining.negative_radius = options.step.triplet.negative_radius;
  learner = std::make_unique<gpl::GplLearner>(
      sensing.gpl.get(), learn, flags.data_dir + "/gpl-learned.pt");
  return std::nullopt;
}

// The SLAM back end's counters, and its session written to the data dir
// (the pose graph closed where the source finished).
absl::Status FinishSlam(const Flags& flags, const Sensing& sensing,
                        const fleetmem::robot::AgentSummary& summary,
                        fleetmem::slam::FleetSlam& slam) {
  const fleetmem::slam::LaserSlamCounters& c = slam.slam().counters();
  std::cerr << absl::StrFormat(
      "[%s] slam: %d scans, %d keyframes, loops %d proposed, %d accepted "
      "(%d inter-robot), %d rejected by geometry, %d by the graph; "
      "%.1f ms SLAM + %.1f ms queries per keyframe\n",
      flags.robot_id, c.scans, c.keyframes, c.loops_proposed, c.loops_accepted,
      c.inter_robot_loops, c.loops_rejected_geometry, c.loops_rejected_graph,
      slam.stats().slam_ms / std::max<uint64_t>(1, c.keyframes),
      slam.stats().query_ms / std::max<uint64_t>(1, c.keyframes));
  absl::Status written =
      summary.source_finished
          ? slam.FinishSession(flags.last > 0 ? flags.last
                                              : sensing.keyframes->size())
          : absl::OkStatus();
  if (written.ok()) written = slam.WriteOutputs(flags.data_dir);
  return written;
}

int Run(const Flags& flags) {
  namespace robot = fleetmem::robot;
  auto report = [](const Failure& failure) {
    std::cerr << "fleetmem-robot: " << failure.message << "\n";
    return failure.exit_code;
  };
  if (Failed failed = CheckFlags(flags)) return report(*failed);
  if (flags.vo) return RunVo(flags);
  fleetmem::slam::FleetSlamOptions slam_options;
  slam_options.slam.keyframe_distance_m = flags.keyframe_distance_m;
  Sensing sensing;
  Clients clients;
  std::unique_ptr<robot::RobotStore> queue;
  if (Failed failed = OpenSensing(flags, slam_options.slam, sensing)) {
    return report(*failed);
  }
  if (Failed failed = Connect(flags, clients)) return report(*failed);
  if (!flags.migrate_from.empty()) {
    if (Failed failed = Migrate(flags, sensing, *clients.setup)) {
      return report(*failed);
    }
  }
  if (Failed failed = OpenQueue(flags, sensing, *clients.setup, queue)) {
    return report(*failed);
  }
  robot::AgentOptions options = MakeAgentOptions(flags, sensing);
  std::cerr << absl::StrFormat(
      "[%s] fleetmem-robot: fleet %s on %s, source %s (%d observations), "
      "encoder %s (%d dims), domain %s, data dir %s%s\n",
      flags.robot_id, flags.fleet, flags.server, sensing.source->description(),
      sensing.source->size(), sensing.encoder->version(),
      sensing.encoder->dimension(), options.domain, flags.data_dir,
      flags.query_only ? ", query only" : "");
  std::unique_ptr<robot::Learner> learner;
  if (Failed failed = MakeLearner(flags, options, sensing, learner)) {
    return report(*failed);
  }
  options.new_upload_client = [upload = clients.upload] {
    return fleetmem::client::Client::Create(upload);
  };
  std::unique_ptr<fleetmem::slam::FleetSlam> slam;
  if (flags.slam) {
    slam_options.fleet_id = flags.fleet;
    slam_options.robot_id = flags.robot_id;
    slam = std::make_unique<fleetmem::slam::FleetSlam>(
        slam_options, sensing.keyframes, sensing.encoder.get(),
        clients.query.get(), flags.first);
  }
  robot::Agent agent(options, clients.agent.get(), clients.query.get(),
                     sensing.source.get(), sensing.encoder.get(), queue.get(),
                     learner.get(), slam.get());
  std::signal(SIGTERM, OnSignal);
  std::signal(SIGINT, OnSignal);
  const absl::Status status = agent.Run(g_stop);
  const robot::AgentSummary summary = agent.summary();
  std::cerr << absl::StrFormat(
      "[%s] summary: %d observations this run (%d in all), %d traces "
      "queued in all, %d uploaded (%d duplicates), %d still queued, %d "
      "segments, replayed %d own + %d peer traces, %d refreshes\n",
      flags.robot_id, summary.observed_this_run, summary.state.observations(),
      summary.state.traces_queued(), summary.state.traces_uploaded(),
      summary.state.upload_duplicates(), summary.queue.depth,
      summary.state.segments(), summary.state.replayed_own(),
      summary.state.replayed_peer(), summary.state.refreshes());
  if (slam) {
    if (absl::Status written = FinishSlam(flags, sensing, summary, *slam);
        !written.ok()) {
      std::cerr << "fleetmem-robot: " << written.ToString() << "\n";
      if (status.ok()) return 1;
    }
  }
  if (!status.ok()) {
    std::cerr << "fleetmem-robot: " << status.ToString() << "\n";
    return 1;
  }
  if (summary.source_finished && !flags.query_only && !summary.drained) {
    return 3;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"fleetmem-robot: one robot of a fleet (docs/robot.md)."};
  fleetmem::common::SetUpProgram(app, "fleetmem-robot");
  Flags flags;
  AddFlags(app, flags);
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  // A mapping robot uploads keyframes in small segments, so that its own
  // and its peers' loop candidates reach the fleet soon.
  if (flags.slam && app.count("--segment-size") == 0) flags.segment_size = 25;
  return Run(flags);
}
