#include "tools/eval/lifelong.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <map>
#include <memory>
#include <numeric>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "Eigen/Dense"
#include "absl/status/statusor.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/learning/gpl_robot.h"
#include "clients/robot/learning/metric_robot.h"
#include "clients/robot/learning/pretrain.h"
#include "clients/robot/learning/segment_learner.h"
#include "clients/robot/memory/dynamic_memory.h"
#include "clients/robot/runtime/fleet_recall.h"
#include "clients/robot/runtime/segment_step.h"
#include "clients/robot/sensing/encoder_factory.h"
#include "clients/robot/sensing/nordland.h"
#include "clients/robot/sensing/rewards.h"
#include "clients/robot/sensing/sequence_search.h"
#include "proto/convert/trace_convert.h"
#include "services/common/files.h"
#include "tools/eval/lifelong_protocol.h"
#include "tools/process/server_process.h"

namespace fleetmem::eval {
namespace {

using lifelong::kAreas;
using lifelong::kDomains;
using lifelong::Score;
using robot::gpl::GplModel;
using robot::gpl::ReplayInput;
using Clock = std::chrono::steady_clock;
using ServerChild = process::ServerProcess;
using Codes = std::vector<std::vector<float>>;

constexpr int kSeasons = 2;
constexpr const char* kSeasonNames[kSeasons] = {"summer", "winter"};
// The fleet code of design (a): the HOG code robots upload (image_encoder.h).
constexpr const char* kFleetCode = "hog-64x32-c8-s8-b6";

// Step budgets, sized for 2 CPU cores (docs/results.md gives the costs).
struct Settings {
  int pretrain_steps;
  // gpl_e2e_joint's L_joint steps on every domain at once.
  int end_to_end_steps;
  int steps_per_segment;
  int generative_steps;
  int seeds;
  int batch_size = 32;
  size_t segment_size = 200;
  size_t replay_per_segment = 128;
  size_t memory_capacity = 1000;
  // *_seq: the robot's last this many frames.
  int sequence_length = 10;
  // gpl_bioslam_decoded: remembered traces decoded per part of the pool
  // (SegmentLearnerOptions::max_decoded_remembered; 0 = all).
  size_t max_decoded_remembered = 0;
};

Settings SettingsFor(bool quick) {
  // --quick checks that every method runs and that its numbers agree with
  // their definitions (check_lifelong.py); its GPL budgets are halved
  // against the issue-44 settings (pre-training 150 steps, L_joint 50, 20
  // place-head steps and 1 generative step a segment, 150 remembered traces
  // decoded a part) to keep the whole run near 6 minutes with 28 methods.
  // The figures in docs/results.md come from the full settings.
  if (quick)
    return Settings{.pretrain_steps = 150,
                    .end_to_end_steps = 50,
                    .steps_per_segment = 20,
                    .generative_steps = 1,
                    .seeds = 1,
                    .max_decoded_remembered = 150};
  return Settings{.pretrain_steps = 300,
                  .end_to_end_steps = 1200,
                  .steps_per_segment = 100,
                  .generative_steps = 10,
                  .seeds = 3};
}

std::string DomainName(int d) {
  return absl::StrCat(kSeasonNames[d / kAreas], " area ", d % kAreas + 1);
}

// The route: frames present in both seasons, in file order.
struct Data {
  std::vector<int> numbers;
  std::vector<cv::Mat> images[kSeasons];
  lifelong::Split split;
  double spacing = 10.0;  // place units between consecutive files

  core::Place PlaceOf(size_t i) const {
    core::Place p;
    p.x = numbers[i];
    return p;
  }
};

absl::StatusOr<Data> LoadData(const std::string& root, int skip_places,
                              int max_places) {
  Data data;
  std::vector<int> lists[kSeasons];
  for (int s = 0; s < kSeasons; ++s) {
    absl::StatusOr<std::vector<int>> frames = robot::ListNordlandFrames(
        absl::StrCat(root, "/nordland/", kSeasonNames[s]));
    if (!frames.ok()) return frames.status();
    lists[s] = *std::move(frames);
  }
  std::set_intersection(lists[0].begin(), lists[0].end(), lists[1].begin(),
                        lists[1].end(), std::back_inserter(data.numbers));
  const size_t skip = std::min(data.numbers.size(), size_t(skip_places));
  data.numbers.erase(data.numbers.begin(), data.numbers.begin() + skip);
  if (max_places > 0 && data.numbers.size() > size_t(max_places)) {
    data.numbers.resize(max_places);
  }
  if (data.numbers.size() < 8 * kAreas) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s/nordland: %d frames are present in both summer and winter (after "
        "skipping %d); the protocol needs at least %d",
        root, data.numbers.size(), skip, 8 * kAreas));
  }
  for (int s = 0; s < kSeasons; ++s) {
    const std::string dir = absl::StrCat(root, "/nordland/", kSeasonNames[s]);
    for (int number : data.numbers) {
      absl::StatusOr<cv::Mat> image = robot::LoadNordlandGrey(dir, number);
      if (!image.ok()) return image.status();
      data.images[s].push_back(*std::move(image));
    }
  }
  data.split = lifelong::SplitRoute(data.numbers.size());
  std::vector<int> gaps;
  for (size_t i = 1; i < data.numbers.size(); ++i)
    gaps.push_back(data.numbers[i] - data.numbers[i - 1]);
  std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2, gaps.end());
  data.spacing = std::max(1, gaps[gaps.size() / 2]);
  return data;
}

Eigen::MatrixXf Matrix(const Codes& rows) {
  const size_t dim = rows.empty() ? 0 : rows[0].size();
  Eigen::MatrixXf m(rows.size(), dim);
  for (size_t r = 0; r < rows.size(); ++r)
    for (size_t c = 0; c < dim; ++c) m(r, c) = rows[r][c];
  return m;
}

// What one method reports for one seed.
struct MethodResult {
  std::string name;
  uint64_t seed = 0;
  // areas[t][a]: area a's winter queries after domain t.
  std::vector<std::vector<Score>> areas;
  lifelong::Summary summary;
  double seconds = 0;
  // Memory methods: the most traces the memory held, and at the end.
  uint64_t peak_traces = 0, final_traces = 0;
  // Segments after which the learner reported a collapsed head.
  int collapses = 0;
};

enum class LearnerKind { kNone, kMetric, kGpl };
enum class MemoryKind { kNone, kFleet, kReservoir };
using robot::RewardMode;

struct MethodSpec {
  std::string name;
  LearnerKind learner = LearnerKind::kMetric;
  bool learn = true;
  // joint: the same learner on every domain's training data at once.
  bool offline = false;
  // *_seq: scored by sequence matching over the robot's last frames
  // (SeqSLAM's search, lifelong_protocol.h) on the method's own single-frame
  // similarities: the code's (classical_seq) or the learned head's.
  bool sequence = false;
  // *_seq_robot: scored instead by the robot's own sequence search
  // (fleetmem-robot --sequence: RankBySequence over each frame's 20 nearest
  // map places, sequence_search.h) on the same similarities.
  bool robot_sequence = false;
  MemoryKind memory = MemoryKind::kNone;
  bool clustering = true;
  bool decay = true;
  // Forgetting merges the closest pair (the server's default) or drops one
  // whole (bioslam_drop: the paper's Algorithm 2).
  bool merge = true;
  // bioslam_pairs, pairs_uniform: the fleet refreshes with the pair-keeping
  // draw (core/pair_draw.h) within the positive radius instead of Eq. 18's;
  // pairs_uniform: its anchors with weight 1 (the fleet's refresh_uniform).
  bool pairs = false;
  bool uniform_refresh = false;
  RewardMode rewards = RewardMode::kFull;
  ReplayInput replay_input = ReplayInput::kCode;
  // bioslam_iw: the metric head weighs remembered traces by 1 / R
  // (MetricRobotLearner's importance weights).
  bool importance_weights = false;
  // gpl_e2e_joint: E, F, G and D trained together (learning.md design (b)).
  bool end_to_end = false;
  // bioslam_rescore: after each segment the robot re-scores its own
  // remembered traces under its new head and the fleet takes their R_ex
  // (UpdateRewards), as fleetmem-robot --rescore does.
  bool rescore = false;
};

// fleet_shared, fleet_shared_pairs, fleet_shared_flat: two robots in one fleet
// (RunFleetShared), reported per robot.
bool IsShared(const MethodSpec& spec) {
  return spec.name.starts_with("fleet_shared");
}

// Report order. bioslam runs before uniform_replay, whose trace budget is
// bioslam's (the same seed's memory, segment by segment). Long (94 lines)
// by its nature: one entry per method of the protocol, in report order.
std::vector<MethodSpec> Specs() {
  using L = LearnerKind;
  using M = MemoryKind;
  std::vector<MethodSpec> specs;
  specs.push_back({.name = "classical", .learner = L::kNone, .learn = false});
  specs.push_back({.name = "classical_seq",
                   .learner = L::kNone,
                   .learn = false,
                   .sequence = true});
  specs.push_back({.name = "classical_seq_robot",
                   .learner = L::kNone,
                   .learn = false,
                   .robot_sequence = true});
  specs.push_back({.name = "joint", .offline = true});
  specs.push_back({.name = "joint_seq", .offline = true, .sequence = true});
  specs.push_back({.name = "finetune"});
  specs.push_back({.name = "bioslam", .memory = M::kFleet});
  specs.push_back(
      {.name = "bioslam_drop", .memory = M::kFleet, .merge = false});
  specs.push_back(
      {.name = "bioslam_iw", .memory = M::kFleet, .importance_weights = true});
  specs.push_back(
      {.name = "bioslam_rescore", .memory = M::kFleet, .rescore = true});
  specs.push_back(
      {.name = "bioslam_seq", .sequence = true, .memory = M::kFleet});
  specs.push_back({.name = "bioslam_seq_robot",
                   .robot_sequence = true,
                   .memory = M::kFleet});
  specs.push_back(
      {.name = "bioslam_pairs", .memory = M::kFleet, .pairs = true});
  // The same with the anchors drawn uniformly (the fleet's
  // refresh_uniform), the robots' rewards as bioslam's.
  specs.push_back({.name = "pairs_uniform",
                   .memory = M::kFleet,
                   .pairs = true,
                   .uniform_refresh = true});
  // And uniform refresh from the fleet's memory without pairs: what the
  // pairs add to it.
  specs.push_back(
      {.name = "fleet_uniform", .memory = M::kFleet, .uniform_refresh = true});
  // Pairs with every reward flat: R = 1 for every trace (the robots'
  // rewards off, so consolidation's downsampling and forgetting do not
  // favour hard traces either) and gamma = 1.
  specs.push_back({.name = "pairs_flat_rewards",
                   .memory = M::kFleet,
                   .decay = false,
                   .pairs = true,
                   .rewards = RewardMode::kUniform});
  specs.push_back({.name = "uniform_replay",
                   .memory = M::kReservoir,
                   .clustering = false,
                   .decay = false,
                   .rewards = RewardMode::kUniform});
  specs.push_back({.name = "uniform_seq",
                   .sequence = true,
                   .memory = M::kReservoir,
                   .clustering = false,
                   .decay = false,
                   .rewards = RewardMode::kUniform});
  specs.push_back({.name = "no_rex",
                   .memory = M::kFleet,
                   .rewards = RewardMode::kNoExternal});
  specs.push_back({.name = "no_rin",
                   .memory = M::kFleet,
                   .rewards = RewardMode::kNoInternal});
  specs.push_back(
      {.name = "no_clustering", .memory = M::kFleet, .clustering = false});
  specs.push_back({.name = "no_decay", .memory = M::kFleet, .decay = false});
  specs.push_back({.name = "fleet_shared", .memory = M::kFleet});
  // fleet_shared with the pair-keeping refresh (bioslam_pairs's rule).
  specs.push_back(
      {.name = "fleet_shared_pairs", .memory = M::kFleet, .pairs = true});
  // ... and with pairs_flat_rewards's.
  specs.push_back({.name = "fleet_shared_flat",
                   .memory = M::kFleet,
                   .decay = false,
                   .pairs = true,
                   .rewards = RewardMode::kUniform});
  specs.push_back(
      {.name = "gpl_pretrained", .learner = L::kGpl, .learn = false});
  specs.push_back({.name = "gpl_joint", .learner = L::kGpl, .offline = true});
  specs.push_back({.name = "gpl_e2e_joint",
                   .learner = L::kGpl,
                   .offline = true,
                   .end_to_end = true});
  specs.push_back({.name = "gpl_finetune", .learner = L::kGpl});
  specs.push_back(
      {.name = "gpl_bioslam", .learner = L::kGpl, .memory = M::kFleet});
  specs.push_back({.name = "gpl_bioslam_decoded",
                   .learner = L::kGpl,
                   .memory = M::kFleet,
                   .replay_input = ReplayInput::kDecoded});
  return specs;
}

void Progress(const std::string& line) {
  std::fprintf(stderr, "%s\n", line.c_str());
  std::fflush(stderr);
}

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

// Every frame's code and R_in (Eq. 12, A = a random shift-crop) under one
// code.
struct CodeSet {
  std::string version;  // the encoder's, carried by every trace
  Codes codes[kSeasons];
  std::vector<float> internal[kSeasons];
};

// Everything one seed's methods share.
struct Context {
  const LifelongOptions* options;
  Settings settings;
  const Data* data;
  uint64_t seed = 1;
  CodeSet hog;
  std::unique_ptr<GplModel> pretrained;
  CodeSet gpl;
  robot::gpl::TripletMiningOptions mining;
  // Traces recalled from the fleet memory per new observation (0 = none).
  uint32_t recall_per_observation = 4;
  std::string server_binary;
  // bioslam's static memory after each segment: uniform_replay's budget.
  std::vector<uint64_t> bioslam_traces;

  const CodeSet& CodesOf(const MethodSpec& spec) const {
    return spec.learner == LearnerKind::kGpl ? gpl : hog;
  }
};

absl::StatusOr<CodeSet> HogCodes(const Data& data, uint64_t seed) {
  absl::StatusOr<std::unique_ptr<robot::Encoder>> hog =
      robot::NewEncoderByName(kFleetCode);
  if (!hog.ok()) return hog.status();
  CodeSet set;
  set.version = (*hog)->version();
  std::mt19937_64 rng(seed);
  for (int s = 0; s < kSeasons; ++s) {
    for (const cv::Mat& image : data.images[s]) {
      robot::Observation o;
      o.image = image;
      absl::StatusOr<std::vector<float>> z = (*hog)->Encode(o);
      if (!z.ok()) return z.status();
      absl::StatusOr<cv::Mat> moved = robot::RandomShiftCrop(image, {}, rng);
      if (!moved.ok()) return moved.status();
      o.image = *moved;
      absl::StatusOr<std::vector<float>> zm = (*hog)->Encode(o);
      if (!zm.ok()) return zm.status();
      set.internal[s].push_back(robot::InternalReward(*z, *zm));
      set.codes[s].push_back(*std::move(z));
    }
  }
  return set;
}

// L_joint training options of the GPL model for one seed.
robot::gpl::PretrainOptions GplPretrainOptions(const Context& ctx) {
  robot::gpl::PretrainOptions options;
  options.model.seed = ctx.seed;
  options.model.code_dimension = ctx.options->code_dimension;
  if (ctx.options->head_learning_rate > 0) {
    options.model.head_learning_rate = ctx.options->head_learning_rate;
  }
  if (ctx.options->gan_weight >= 0)
    options.model.gan_weight = float(ctx.options->gan_weight);
  options.version =
      absl::StrFormat("gpl-64x32-d%d-s%d-p%d-v1", options.model.code_dimension,
                      ctx.seed, ctx.settings.pretrain_steps);
  options.steps = ctx.settings.pretrain_steps;
  options.batch_size = ctx.settings.batch_size / 2;
  options.positive_radius = ctx.mining.positive_radius;
  options.negative_radius = ctx.mining.negative_radius;
  options.seed = ctx.seed;
  options.log = [](std::string_view line) { Progress(std::string(line)); };
  return options;
}

// Pre-training of the GPL fleet encoder (learning.md: trained once on the
// initial domain, then frozen): L_joint (Eq. 10) on summer area 1's
// training frames, then every frame is encoded once.
absl::Status PretrainGpl(Context& ctx) {
  const Data& data = *ctx.data;
  const robot::gpl::PretrainOptions options = GplPretrainOptions(ctx);
  std::vector<cv::Mat> images;
  std::vector<double> positions;
  for (size_t i : data.split.Places(0, false)) {
    images.push_back(data.images[0][i]);
    positions.push_back(data.numbers[i]);
  }
  const auto start = Clock::now();
  absl::StatusOr<std::unique_ptr<GplModel>> model =
      robot::gpl::PretrainFleetEncoder(images, positions, options);
  if (!model.ok()) return model.status();
  std::mt19937_64 rng(ctx.seed);
  ctx.pretrained = *std::move(model);
  if (absl::Status s = ctx.pretrained->Save(absl::StrFormat(
          "%s/encoder-seed%d.pt", ctx.options->out_dir, ctx.seed));
      !s.ok()) {
    return s;
  }
  for (int s = 0; s < kSeasons; ++s) {
    absl::StatusOr<Codes> z = ctx.pretrained->Encode(data.images[s]);
    if (!z.ok()) return z.status();
    ctx.gpl.codes[s] = *std::move(z);
    std::vector<cv::Mat> moved;
    for (const cv::Mat& image : data.images[s]) {
      absl::StatusOr<cv::Mat> m = robot::RandomShiftCrop(image, {}, rng);
      if (!m.ok()) return m.status();
      moved.push_back(*std::move(m));
    }
    absl::StatusOr<Codes> zm = ctx.pretrained->Encode(moved);
    if (!zm.ok()) return zm.status();
    for (size_t i = 0; i < moved.size(); ++i) {
      ctx.gpl.internal[s].push_back(
          robot::InternalReward(ctx.gpl.codes[s][i], (*zm)[i]));
    }
  }
  Progress(absl::StrFormat(
      "[pretrain] GPL fleet encoder %s frozen: %d parameters, %.0f s",
      ctx.pretrained->version(), ctx.pretrained->ParameterCount(),
      Seconds(start)));
  return absl::OkStatus();
}

// uniform_replay's memory: a uniform sample of every trace the robot made
// (reservoir sampling), held to a budget that may change between segments.
class Reservoir {
 public:
  explicit Reservoir(uint64_t seed) : rng_(seed) {}

  void Add(const core::MemoryTrace& t, size_t budget) {
    ++seen_;
    if (traces_.size() < budget) {
      traces_.push_back(t);
    } else if (budget > 0) {
      const uint64_t j =
          std::uniform_int_distribution<uint64_t>(0, seen_ - 1)(rng_);
      if (j < budget) traces_[j % traces_.size()] = t;
    }
    Shrink(budget);
  }
  void Shrink(size_t budget) {
    while (traces_.size() > budget) {
      const size_t j =
          std::uniform_int_distribution<size_t>(0, traces_.size() - 1)(rng_);
      traces_[j] = traces_.back();
      traces_.pop_back();
    }
  }
  // Up to `count` distinct traces, uniformly.
  std::vector<core::MemoryTrace> Sample(size_t count) {
    std::vector<size_t> order(traces_.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = i;
    std::shuffle(order.begin(), order.end(), rng_);
    order.resize(std::min(count, order.size()));
    std::vector<core::MemoryTrace> out;
    for (size_t i : order) out.push_back(traces_[i]);
    return out;
  }
  // The k traces nearest to `code` (cosine) within `radius` of `place`: the
  // same recall QueryPlace gives the fleet's memory.
  std::vector<core::MemoryTrace> Recall(const std::vector<float>& code,
                                        const core::Place& place, size_t k,
                                        double radius) const {
    std::vector<std::pair<double, size_t>> near;
    for (size_t i = 0; i < traces_.size(); ++i) {
      const core::Place& p = traces_[i].place;
      const double dx = p.x - place.x, dy = p.y - place.y, dz = p.z - place.z;
      if (dx * dx + dy * dy + dz * dz > radius * radius) continue;
      double dot = 0, a = 0, b = 0;
      for (size_t c = 0; c < code.size(); ++c) {
        dot += code[c] * traces_[i].code[c];
        a += code[c] * code[c];
        b += traces_[i].code[c] * traces_[i].code[c];
      }
      near.push_back({-dot / std::sqrt(std::max(a * b, 1e-30)), i});
    }
    const size_t n = std::min(k, near.size());
    std::partial_sort(near.begin(), near.begin() + n, near.end());
    std::vector<core::MemoryTrace> out;
    for (size_t j = 0; j < n; ++j) out.push_back(traces_[near[j].second]);
    return out;
  }
  size_t size() const { return traces_.size(); }

 private:
  std::vector<core::MemoryTrace> traces_;
  uint64_t seen_ = 0;
  std::mt19937_64 rng_;
};

// One robot of a method: its learner and dynamic memory.
struct Robot {
  std::string id;
  std::string code_version;
  // The GPL learner's model (null for the metric head).
  std::unique_ptr<robot::gpl::SharedModel> model;
  std::unique_ptr<robot::Learner> learner;
  std::unique_ptr<robot::DynamicMemory> memory;
  std::unique_ptr<Reservoir> reservoir;
  uint64_t next_seq = 1;
  size_t segments = 0;
  std::mt19937_64 rng;
  std::string last;
  uint64_t peak_traces = 0, traces = 0;
};

robot::gpl::SegmentLearnerOptions GplLearnerOptions(const Context& ctx,
                                                    const MethodSpec& spec,
                                                    uint64_t seed) {
  robot::gpl::SegmentLearnerOptions lo;
  lo.steps_per_segment = ctx.settings.steps_per_segment;
  lo.batch_size = ctx.settings.batch_size;
  lo.replay_input = spec.replay_input;
  lo.generative_steps_per_segment = spec.replay_input == ReplayInput::kDecoded
                                        ? ctx.settings.generative_steps
                                        : 0;
  lo.mining = ctx.mining;
  lo.max_decoded_remembered = ctx.settings.max_decoded_remembered;
  lo.seed = seed;
  return lo;
}

// The GPL learner on a copy of the fleet's frozen encoder and its head.
absl::Status UseGplLearner(Context& ctx,
                           const robot::gpl::SegmentLearnerOptions& options,
                           Robot& r) {
  absl::StatusOr<std::unique_ptr<GplModel>> model = ctx.pretrained->Clone();
  if (!model.ok()) return model.status();
  r.code_version = (*model)->version();
  r.learner.reset();
  r.model = std::make_unique<robot::gpl::SharedModel>();
  {
    absl::MutexLock lock(&r.model->mu);
    r.model->model = *std::move(model);
  }
  r.learner = std::make_unique<robot::gpl::GplLearner>(r.model.get(), options);
  return absl::OkStatus();
}

absl::StatusOr<Robot> NewRobot(Context& ctx, const MethodSpec& spec,
                               const std::string& id, uint64_t seed) {
  Robot r;
  r.id = id;
  if (spec.learner == LearnerKind::kGpl) {
    absl::Status s = UseGplLearner(ctx, GplLearnerOptions(ctx, spec, seed), r);
    if (!s.ok()) return s;
  } else {
    robot::gpl::MetricHeadOptions mo;
    mo.pair_radius = ctx.mining.positive_radius;
    mo.mining = ctx.mining;
    if (ctx.options->metric_update_rate > 0)
      mo.update_rate = ctx.options->metric_update_rate;
    if (ctx.options->metric_partners > 0)
      mo.max_partners = ctx.options->metric_partners;
    r.code_version = ctx.hog.version;
    r.learner = std::make_unique<robot::gpl::MetricRobotLearner>(
        robot::gpl::MetricHead(int(ctx.hog.codes[0].front().size()), mo), "",
        spec.importance_weights);
  }
  robot::DynamicMemoryOptions mo;
  mo.capacity = ctx.settings.memory_capacity;
  mo.gamma = spec.decay ? 0.9 : 1.0;
  r.memory = std::make_unique<robot::DynamicMemory>(id, mo);
  r.reservoir = std::make_unique<Reservoir>(seed + 101);
  r.rng.seed(seed);
  return r;
}

// The place recall of RunSegment's step: the k remembered traces nearest
// to an observation's code within the pair radius of its place, from the
// fleet's memory (QueryPlace with a position prior) or the reservoir.
robot::PlaceRecall RecallFor(const Context& ctx, const MethodSpec& spec,
                             Robot& r, client::Client* client,
                             const std::string& fleet) {
  const double radius = ctx.mining.positive_radius;
  if (spec.memory == MemoryKind::kReservoir) {
    return [&r, radius](
               const core::MemoryTrace& x,
               size_t k) -> absl::StatusOr<std::vector<core::MemoryTrace>> {
      return r.reservoir->Recall(x.code, x.place, k, radius);
    };
  }
  return robot::NewFleetRecall(client, fleet, radius);
}

// A segment's new traces (the robot's frames as the method encodes them),
// and their observations when the replay decodes images.
std::vector<core::MemoryTrace> SegmentTraces(
    Context& ctx, const MethodSpec& spec, Robot& r, int season,
    const std::vector<size_t>& segment,
    std::vector<robot::Observation>* observations) {
  const CodeSet& codes = ctx.CodesOf(spec);
  std::vector<core::MemoryTrace> fresh;
  for (size_t i : segment) {
    core::MemoryTrace& t = fresh.emplace_back();
    t.robot_id = r.id;
    t.seq = r.next_seq++;
    t.domain = kSeasonNames[season];
    t.code = codes.codes[season][i];
    t.place = ctx.data->PlaceOf(i);
    t.reward_internal = codes.internal[season][i];
    t.timestamp_ns = int64_t(t.seq);
    t.encoder_version = r.code_version;
    if (spec.replay_input == ReplayInput::kDecoded) {
      robot::Observation& o = observations->emplace_back();
      o.index = i;
      o.place = t.place;
      o.image = ctx.data->images[season][i];
    }
  }
  return fresh;
}

// After a segment's step: its traces into the method's memory (the fleet's:
// upload, consolidate, the re-scored traces; uniform_replay's reservoir at
// bioslam's budget), and the draw that refreshes M_D.
absl::StatusOr<std::vector<core::MemoryTrace>> IntoMemory(
    Context& ctx, const MethodSpec& spec, Robot& r, size_t segment_index,
    const robot::SegmentStepResult& step, client::Client* client,
    const std::string& fleet) {
  const std::vector<core::MemoryTrace>& own = step.traces;
  std::vector<core::MemoryTrace> refreshed;
  if (spec.memory == MemoryKind::kReservoir) {
    if (ctx.bioslam_traces.empty()) {
      return absl::FailedPreconditionError(
          "uniform_replay's budget is bioslam's memory: run bioslam first");
    }
    const size_t budget = ctx.bioslam_traces[std::min(
        segment_index, ctx.bioslam_traces.size() - 1)];
    for (const core::MemoryTrace& t : own) r.reservoir->Add(t, budget);
    // Also without new traces: bioslam's memory may have shrunk.
    r.reservoir->Shrink(budget);
    r.traces = r.reservoir->size();
    return r.reservoir->Sample(ctx.settings.memory_capacity);
  }
  std::vector<v1::MemoryTrace> traces;
  for (const core::MemoryTrace& t : own)
    api::TraceToProto(t, &traces.emplace_back());
  absl::StatusOr<v1::UploadTracesResponse> uploaded =
      client->Upload(fleet, traces);
  if (!uploaded.ok()) return uploaded.status();
  absl::StatusOr<v1::ConsolidateResponse> consolidated =
      client->Consolidate(fleet);
  if (!consolidated.ok()) return consolidated.status();
  r.traces = consolidated->traces();
  // bioslam_rescore: the robot's own remembered traces, re-scored by the
  // step, to the fleet (after they were uploaded) and to M_D.
  if (!step.rescored.empty()) {
    absl::StatusOr<v1::UpdateRewardsResponse> sent =
        robot::SendRescored(*client, fleet, step.rescored, *r.memory);
    if (!sent.ok()) return sent.status();
  }
  absl::StatusOr<std::vector<v1::MemoryTrace>> sampled =
      client->SampleReplay(fleet, r.id, uint32_t(ctx.settings.memory_capacity));
  if (!sampled.ok()) return sampled.status();
  for (const v1::MemoryTrace& t : *sampled)
    refreshed.push_back(api::TraceFromProto(t));
  return refreshed;
}

// Algorithm 3 for one segment of one robot: the robot's own segment step
// (clients/robot/runtime/segment_step.h: replay, recall, learn, rewards), then
// upload and consolidate (or, for uniform_replay, keep a uniform sample)
// and refresh M_D.
absl::Status RunSegment(Context& ctx, const MethodSpec& spec, Robot& r,
                        int season, const std::vector<size_t>& segment,
                        client::Client* client, const std::string& fleet) {
  std::vector<robot::Observation> observations;
  std::vector<core::MemoryTrace> fresh =
      SegmentTraces(ctx, spec, r, season, segment, &observations);
  robot::SegmentStepOptions step_options;
  step_options.replay_per_segment = ctx.settings.replay_per_segment;
  step_options.rewards = spec.rewards;
  step_options.rescore_remembered = spec.rescore;
  step_options.recall_per_observation =
      spec.memory == MemoryKind::kNone ? 0 : ctx.recall_per_observation;
  const robot::PlaceRecall recall =
      spec.memory == MemoryKind::kNone ? robot::PlaceRecall()
                                       : RecallFor(ctx, spec, r, client, fleet);
  absl::StatusOr<robot::SegmentStepResult> step =
      robot::RunSegmentStep(step_options, std::move(fresh), observations,
                            *r.memory, r.rng, r.learner.get(), recall);
  if (!step.ok()) return step.status();
  r.last = step->report;
  const size_t segment_index = r.segments++;
  if (spec.memory == MemoryKind::kNone) return absl::OkStatus();
  absl::StatusOr<std::vector<core::MemoryTrace>> refreshed =
      IntoMemory(ctx, spec, r, segment_index, *step, client, fleet);
  if (!refreshed.ok()) return refreshed.status();
  r.peak_traces = std::max(r.peak_traces, r.traces);
  for (const core::MemoryTrace& t : step->traces) r.memory->AddOwn(t);
  r.memory->Refresh(*refreshed);
  return absl::OkStatus();
}

std::vector<std::vector<size_t>> Segments(const std::vector<size_t>& indices,
                                          size_t size) {
  std::vector<std::vector<size_t>> out;
  for (size_t b = 0; b < indices.size(); b += size) {
    out.emplace_back(indices.begin() + b,
                     indices.begin() + std::min(indices.size(), b + size));
  }
  return out;
}

// The server configuration of `spec`'s memory (clustering, decay, the
// forgetting rule, the refresh draw) for this seed, written at each start.
absl::StatusOr<std::string> ConfigFile(const Context& ctx,
                                       const MethodSpec& spec) {
  const std::string path =
      absl::StrFormat("%s/server-c%d-d%d-m%d-p%d-u%d-seed%d.textproto",
                      ctx.options->out_dir, spec.clustering, spec.decay,
                      spec.merge, spec.pairs, spec.uniform_refresh, ctx.seed);
  absl::Status s = files::WriteFile(
      path,
      absl::StrFormat("log_level: \"warning\"\nmemory {\n  clustering: %s\n"
                      "  replay_decay: %s\n  merge_on_forget: %s\n  seed: %d\n"
                      "  refresh_pair_radius: %g\n  refresh_uniform: %s\n%s}\n",
                      spec.clustering ? "true" : "false",
                      spec.decay ? "0.9" : "1", spec.merge ? "true" : "false",
                      ctx.seed, spec.pairs ? ctx.mining.positive_radius : 0.0,
                      spec.uniform_refresh ? "true" : "false",
                      ctx.options->spatial_scale > 0
                          ? absl::StrFormat("  spatial_scale_m: %g\n",
                                            ctx.options->spatial_scale)
                          : ""));
  if (!s.ok()) return s;
  return path;
}

// A server child with the method's memory configuration.
absl::StatusOr<std::unique_ptr<ServerChild>> StartServer(
    Context& ctx, const MethodSpec& spec) {
  const std::string dir = absl::StrFormat(
      "%s/servers/%s-seed%d", ctx.options->out_dir, spec.name, ctx.seed);
  std::error_code ec;
  std::filesystem::remove_all(dir, ec);
  std::filesystem::create_directories(dir + "/data", ec);
  if (ec)
    return absl::InternalError(
        absl::StrCat("cannot create ", dir, ": ", ec.message()));
  process::ServerOptions options;
  options.binary = ctx.server_binary;
  options.data_dir = dir + "/data";
  absl::StatusOr<std::string> config = ConfigFile(ctx, spec);
  if (!config.ok()) return config.status();
  options.config_file = *config;
  options.log_file = dir + "/server.log";
  auto server = std::make_unique<ServerChild>(options);
  absl::Status started = server->Start();
  if (!started.ok()) return started;
  return server;
}

// Stops a server child; INTERNAL unless it exits cleanly on SIGTERM.
absl::Status StopServer(ServerChild& server) {
  absl::StatusOr<int> code = server.Stop();
  if (!code.ok()) return code.status();
  if (*code != 0) {
    return absl::InternalError(
        absl::StrCat("the server exited with ", *code,
                     " on SIGTERM; its log: ", server.options().log_file));
  }
  return absl::OkStatus();
}

std::unique_ptr<client::Client> Connect(const ServerChild& server) {
  client::ClientOptions o;
  o.target = server.address();
  o.deadline = std::chrono::milliseconds(60000);
  return client::Client::Create(o);
}

// Every area's winter queries against the summer map, both described by
// `learner` (or the raw codes when it is null); with `sequence`, their
// single-frame similarities matched as sequences of the robot's last
// frames (SequenceSimilarity) before the areas are scored.
// The robot's sequence search (fleetmem-robot --sequence) on the protocol:
// every winter frame in route order takes its `candidates` most similar
// summer places (`similarity` row), the window of its last
// `length` frames is searched (RankBySequence, the distance travelled
// between frames from their places, tolerance `radius`), and the row is
// rewritten so that the re-ranked candidates come first in their new order.
Eigen::MatrixXf RobotSequenceRows(const Data& data,
                                  const Eigen::MatrixXf& similarity,
                                  size_t length, double radius,
                                  size_t candidates_per_frame) {
  const Eigen::Index n = similarity.rows(), m = similarity.cols();
  Eigen::MatrixXf out =
      Eigen::MatrixXf::Constant(n, m, -std::numeric_limits<float>::max());
  robot::SequenceWindow window(length);
  std::vector<Eigen::Index> order(m);
  for (Eigen::Index q = 0; q < n; ++q) {
    std::iota(order.begin(), order.end(), Eigen::Index{0});
    const size_t k = std::min<size_t>(candidates_per_frame, size_t(m));
    std::partial_sort(order.begin(), order.begin() + k, order.end(),
                      [&](Eigen::Index a, Eigen::Index b) {
                        return similarity(q, a) > similarity(q, b);
                      });
    std::vector<robot::SequenceCandidate> candidates;
    for (size_t c = 0; c < k; ++c) {
      candidates.push_back({.place = data.PlaceOf(size_t(order[c])),
                            .distance = 1.0f - similarity(q, order[c])});
    }
    window.Add(data.PlaceOf(size_t(q)), candidates);
    const std::vector<size_t> ranked = robot::RankBySequence(
        window.frames(), {.length = length, .tolerance = radius});
    for (size_t r = 0; r < ranked.size(); ++r) {
      out(q, order[ranked[r]]) = float(k - r);
    }
  }
  return out;
}

absl::StatusOr<std::vector<Score>> Evaluate(const Context& ctx,
                                            const CodeSet& codes,
                                            robot::Learner* learner,
                                            bool sequence,
                                            bool robot_sequence = false) {
  Eigen::MatrixXf rows[kSeasons];
  for (int s = 0; s < kSeasons; ++s) {
    if (learner == nullptr) {
      rows[s] = lifelong::UnitRows(Matrix(codes.codes[s]));
      continue;
    }
    absl::StatusOr<Codes> d = learner->Describe(codes.codes[s]);
    if (!d.ok()) return d.status();
    rows[s] = lifelong::UnitRows(Matrix(*d));
  }
  if (!sequence && !robot_sequence) {
    return lifelong::ScoreAreas(ctx.data->split, rows[0], rows[1]);
  }
  const Eigen::MatrixXf seq =
      robot_sequence
          ? RobotSequenceRows(*ctx.data, rows[1] * rows[0].transpose(),
                              size_t(ctx.settings.sequence_length),
                              ctx.mining.positive_radius,
                              size_t(ctx.options->sequence_candidates))
          : lifelong::SequenceSimilarity(rows[1] * rows[0].transpose(),
                                         ctx.settings.sequence_length);
  std::vector<Score> scores;
  for (int a = 0; a < kAreas; ++a) {
    const std::vector<size_t> places = ctx.data->split.Places(a, true);
    Eigen::MatrixXf queries(places.size(), seq.cols());
    for (size_t r = 0; r < places.size(); ++r) {
      queries.row(r) = seq.row(places[r]);
    }
    scores.push_back(lifelong::ScoreQueries(queries, places));
  }
  return scores;
}

// gpl_e2e_joint, the ceiling of learning.md's design (b): the GPL model
// trained end to end, L_joint (Eq. 10; L_gan off by default) on E, F, G
// and D, on every domain's
// training frames at once -- both seasons of each training place, triplets
// by place, so a place's summer and winter frames are positives of each
// other -- from the initial weights of the fleet encoder's pre-training and
// with its augmentation; then every frame is encoded and described by the
// trained model (its codes are a new version: a fleet using it re-encodes).
absl::StatusOr<std::vector<Score>> EndToEndJoint(Context& ctx) {
  const Data& data = *ctx.data;
  robot::gpl::PretrainOptions options = GplPretrainOptions(ctx);
  options.steps = ctx.settings.end_to_end_steps;
  // L_loc + L_rec without the adversarial term unless --gan-weight says
  // otherwise: the ceiling needs no generative replay, and with it the
  // triplet loss stayed at the margin (docs/results.md).
  if (ctx.options->gan_weight < 0) options.model.gan_weight = 0.0f;
  options.version =
      absl::StrFormat("gpl-e2e-joint-s%d-p%d", ctx.seed, options.steps);
  std::vector<cv::Mat> images;
  std::vector<double> positions;
  for (int t = 0; t < kDomains; ++t) {
    for (size_t i : data.split.Places(t % kAreas, false)) {
      images.push_back(data.images[t / kAreas][i]);
      positions.push_back(data.numbers[i]);
    }
  }
  const auto start = Clock::now();
  absl::StatusOr<std::unique_ptr<GplModel>> model =
      robot::gpl::PretrainFleetEncoder(images, positions, options);
  if (!model.ok()) return model.status();
  // Scored twice: by the place head's descriptors F(z) (the method's
  // figure) and, for the log, by the trained codes z themselves (cosine),
  // which keep the image's layout that NetVLAD's orderless pooling drops.
  Eigen::MatrixXf rows[kSeasons], code_rows[kSeasons];
  for (int s = 0; s < kSeasons; ++s) {
    absl::StatusOr<Codes> z = (*model)->Encode(data.images[s]);
    if (!z.ok()) return z.status();
    Codes described;
    for (size_t begin = 0; begin < z->size(); begin += 1024) {
      const size_t n = std::min<size_t>(1024, z->size() - begin);
      absl::StatusOr<Codes> d = (*model)->Describe(
          std::span<const std::vector<float>>(*z).subspan(begin, n));
      if (!d.ok()) return d.status();
      for (auto& row : *d) described.push_back(std::move(row));
    }
    rows[s] = lifelong::UnitRows(Matrix(described));
    code_rows[s] = lifelong::UnitRows(Matrix(*z));
  }
  const std::vector<Score> by_code =
      lifelong::ScoreAreas(data.split, code_rows[0], code_rows[1]);
  Progress(absl::StrFormat(
      "[gpl_e2e_joint seed %d] %d L_joint steps on %d frames of both seasons "
      "(%.0f s); winter WR by area with the trained codes z (cosine): %.3f "
      "%.3f %.3f",
      ctx.seed, options.steps, images.size(), Seconds(start), by_code[0].wr,
      by_code[1].wr, by_code[2].wr));
  return lifelong::ScoreAreas(data.split, rows[0], rows[1]);
}

// Methods that do not learn over the domains (classical, classical_seq,
// gpl_pretrained, joint): one score, the same after every domain.
absl::StatusOr<MethodResult> RunStatic(Context& ctx, const MethodSpec& spec) {
  MethodResult result;
  result.name = spec.name;
  result.seed = ctx.seed;
  const auto start = Clock::now();
  const CodeSet& codes = ctx.CodesOf(spec);
  std::vector<Score> scores;
  if (spec.end_to_end) {
    absl::StatusOr<std::vector<Score>> s = EndToEndJoint(ctx);
    if (!s.ok()) return s.status();
    scores = *s;
  } else if (spec.learner == LearnerKind::kNone) {
    absl::StatusOr<std::vector<Score>> s =
        Evaluate(ctx, codes, nullptr, spec.sequence, spec.robot_sequence);
    if (!s.ok()) return s.status();
    scores = *s;
  } else {
    absl::StatusOr<Robot> robot = NewRobot(ctx, spec, "robot-1", ctx.seed + 17);
    if (!robot.ok()) return robot.status();
    if (spec.offline) {
      // joint: every domain's training samples at once, with the step
      // budget of all the segments the continual methods see.
      std::vector<core::MemoryTrace> all;
      size_t segments = 0;
      for (int t = 0; t < kDomains; ++t) {
        const int season = t / kAreas;
        const std::vector<size_t> places =
            ctx.data->split.Places(t % kAreas, false);
        segments += Segments(places, ctx.settings.segment_size).size();
        for (size_t i : places) {
          core::MemoryTrace& x = all.emplace_back();
          x.robot_id = robot->id;
          x.seq = all.size();
          x.domain = kSeasonNames[season];
          x.code = codes.codes[season][i];
          x.place = ctx.data->PlaceOf(i);
        }
      }
      if (spec.learner == LearnerKind::kGpl) {
        robot::gpl::SegmentLearnerOptions lo =
            GplLearnerOptions(ctx, spec, ctx.seed + 17);
        lo.steps_per_segment = int(segments) * ctx.settings.steps_per_segment;
        if (absl::Status s = UseGplLearner(ctx, lo, *robot); !s.ok()) return s;
      }
      absl::StatusOr<std::string> report =
          robot->learner->Learn(all, {}, {}, {});
      if (!report.ok()) return report.status();
      if (absl::StrContains(*report, "COLLAPSED")) ++result.collapses;
      Progress(absl::StrFormat("[%s] offline on %d samples: %s", spec.name,
                               all.size(), *report));
    }
    absl::StatusOr<std::vector<Score>> s = Evaluate(
        ctx, codes, robot->learner.get(), spec.sequence, spec.robot_sequence);
    if (!s.ok()) return s.status();
    scores = *s;
  }
  result.areas.assign(kDomains, scores);
  result.summary = lifelong::Summarise(result.areas);
  result.seconds = Seconds(start);
  return result;
}

absl::StatusOr<MethodResult> RunSingleRobot(Context& ctx,
                                            const MethodSpec& spec) {
  if (!spec.learn || spec.offline) return RunStatic(ctx, spec);
  MethodResult result;
  result.name = spec.name;
  result.seed = ctx.seed;
  const auto start = Clock::now();
  std::unique_ptr<ServerChild> server;
  std::unique_ptr<client::Client> client;
  if (spec.memory == MemoryKind::kFleet) {
    absl::StatusOr<std::unique_ptr<ServerChild>> s = StartServer(ctx, spec);
    if (!s.ok()) return s.status();
    server = *std::move(s);
    client = Connect(*server);
  }
  absl::StatusOr<Robot> robot = NewRobot(ctx, spec, "robot-1", ctx.seed + 17);
  if (!robot.ok()) return robot.status();
  std::vector<uint64_t> traces_after_segment;
  for (int t = 0; t < kDomains; ++t) {
    const int season = t / kAreas;
    const auto segments = Segments(ctx.data->split.Places(t % kAreas, false),
                                   ctx.settings.segment_size);
    for (const auto& segment : segments) {
      absl::Status s = RunSegment(ctx, spec, *robot, season, segment,
                                  client.get(), spec.name);
      if (!s.ok()) return s;
      traces_after_segment.push_back(robot->traces);
      if (absl::StrContains(robot->last, "COLLAPSED")) ++result.collapses;
    }
    absl::StatusOr<std::vector<Score>> scores =
        Evaluate(ctx, ctx.CodesOf(spec), robot->learner.get(), spec.sequence,
                 spec.robot_sequence);
    if (!scores.ok()) return scores.status();
    result.areas.push_back(*scores);
    Progress(absl::StrFormat(
        "[%s seed %d] domain %d/%d (%s): %d segments, last: %s; memory %d "
        "traces, M_D %d; winter WR by area %.3f %.3f %.3f (%.0f s)",
        spec.name, ctx.seed, t + 1, kDomains, DomainName(t), segments.size(),
        robot->last, robot->traces, robot->memory->size(), (*scores)[0].wr,
        (*scores)[1].wr, (*scores)[2].wr, Seconds(start)));
  }
  if (server) {
    if (absl::Status s = StopServer(*server); !s.ok()) return s;
  }
  if (spec.name == "bioslam") ctx.bioslam_traces = traces_after_segment;
  result.summary = lifelong::Summarise(result.areas);
  result.peak_traces = robot->peak_traces;
  result.final_traces = robot->traces;
  result.seconds = Seconds(start);
  return result;
}

// fleet_shared: robot A drives area 1, robot B area 2, summer then winter,
// segments interleaved, through one fleet memory; each is compared with
// itself driving alone (a fleet of its own) on the area only the peer drove.
struct FleetRow {
  std::string method;
  uint64_t seed = 0;
  std::string robot;
  int own_area = 0, peer_area = 0;
  double own_wr = 0, peer_wr_shared = 0, peer_wr_alone = 0, peer_own_wr = 0;
};

// The robot's scores on every area, with its learner.
absl::Status EvaluateRobot(Context& ctx, const MethodSpec& spec,
                           const Robot& robot, std::vector<Score>* scores) {
  absl::StatusOr<std::vector<Score>> evaluated =
      Evaluate(ctx, ctx.CodesOf(spec), robot.learner.get(), spec.sequence);
  if (!evaluated.ok()) return evaluated.status();
  *scores = *std::move(evaluated);
  return absl::OkStatus();
}

// The warm start (issue 47), after the fleet-shared drives: robot C joins
// the fleet and is scored on its peers' areas (A's and B's: places C never
// drove) with HOG, after its warm start (its head fitted on its first
// refresh, before any frame: robot::WarmStart) and after its first segment
// on its own area (the third, summer); beside it the same robot after the
// same segment without the warm start (in the fleet: "cold") and in a fleet
// of its own ("alone"). The cold robot's segment reaches the fleet after
// the warm one's (each uploads its own traces under its own id).
struct WarmRow {
  std::string method;
  uint64_t seed = 0;
  double hog = 0, warm = 0, warm_first_segment = 0, cold_first_segment = 0,
         alone_first_segment = 0;
};

absl::StatusOr<WarmRow> RunWarmStart(Context& ctx, const MethodSpec& spec,
                                     client::Client* client,
                                     const std::string& fleet) {
  constexpr int kOwnArea = 2;
  auto peers_wr = [](const std::vector<Score>& s) {
    return (s[0].wr + s[1].wr) / 2;
  };
  WarmRow row;
  row.method = spec.name;
  row.seed = ctx.seed;
  absl::StatusOr<std::vector<Score>> hog =
      Evaluate(ctx, ctx.hog, nullptr, spec.sequence);
  if (!hog.ok()) return hog.status();
  row.hog = peers_wr(*hog);
  std::vector<Robot> robots;  // warm, cold, alone: the same seed
  for (const char* id : {"robot-c", "robot-c-cold", "robot-c-alone"}) {
    absl::StatusOr<Robot> r = NewRobot(ctx, spec, id, ctx.seed + 41);
    if (!r.ok()) return r.status();
    robots.push_back(*std::move(r));
  }
  Robot& warm = robots[0];
  for (Robot* r : {&robots[0], &robots[1]}) {
    absl::StatusOr<std::vector<v1::MemoryTrace>> sampled = client->SampleReplay(
        fleet, r->id, uint32_t(ctx.settings.memory_capacity));
    if (!sampled.ok()) return sampled.status();
    std::vector<core::MemoryTrace> refreshed;
    for (const v1::MemoryTrace& t : *sampled) {
      refreshed.push_back(api::TraceFromProto(t));
    }
    r->memory->Refresh(refreshed);
  }
  absl::StatusOr<std::string> warmed =
      robot::WarmStart(*warm.learner, *warm.memory);
  if (!warmed.ok()) return warmed.status();
  std::vector<Score> scores;
  if (absl::Status s = EvaluateRobot(ctx, spec, warm, &scores); !s.ok()) {
    return s;
  }
  row.warm = peers_wr(scores);
  const std::vector<size_t> first = Segments(
      ctx.data->split.Places(kOwnArea, false), ctx.settings.segment_size)[0];
  double* after[3] = {&row.warm_first_segment, &row.cold_first_segment,
                      &row.alone_first_segment};
  for (size_t k = 0; k < robots.size(); ++k) {
    const std::string to = k < 2 ? fleet : "alone-robot-c";
    if (absl::Status s =
            RunSegment(ctx, spec, robots[k], /*season=*/0, first, client, to);
        !s.ok()) {
      return s;
    }
    if (absl::Status s = EvaluateRobot(ctx, spec, robots[k], &scores);
        !s.ok()) {
      return s;
    }
    *after[k] = peers_wr(scores);
  }
  Progress(absl::StrFormat(
      "[%s seed %d] a new robot on its peers' areas: HOG %.3f; warm start "
      "%.3f before any frame (%s), %.3f after its first segment; without "
      "the warm start %.3f, alone %.3f after it",
      spec.name, ctx.seed, row.hog, row.warm, *warmed, row.warm_first_segment,
      row.cold_first_segment, row.alone_first_segment));
  return row;
}

// fleet_shared's two robots scored on both areas, shared and alone: their
// rows, and the method's summary (WR over both areas, AE on its own, RA on
// its peer's).
absl::Status ScoreFleetShared(Context& ctx, const MethodSpec& spec,
                              const int (&areas)[2], std::vector<Robot>& shared,
                              std::vector<Robot>& alone,
                              std::vector<FleetRow>* rows,
                              MethodResult* result) {
  std::vector<Score> s_shared[2], s_alone[2];
  for (int k = 0; k < 2; ++k) {
    absl::Status evaluated = EvaluateRobot(ctx, spec, shared[k], &s_shared[k]);
    if (evaluated.ok()) {
      evaluated = EvaluateRobot(ctx, spec, alone[k], &s_alone[k]);
    }
    if (!evaluated.ok()) return evaluated;
  }
  double wr_sum = 0, own_sum = 0, peer_sum = 0;
  for (int k = 0; k < 2; ++k) {
    const int p = 1 - k;
    FleetRow row;
    row.method = spec.name;
    row.seed = ctx.seed;
    row.robot = shared[k].id;
    row.own_area = areas[k] + 1;
    row.peer_area = areas[p] + 1;
    row.own_wr = s_shared[k][areas[k]].wr;
    row.peer_wr_shared = s_shared[k][areas[p]].wr;
    row.peer_wr_alone = s_alone[k][areas[p]].wr;
    row.peer_own_wr = s_shared[p][areas[p]].wr;
    rows->push_back(row);
    wr_sum += (row.own_wr + row.peer_wr_shared) / 2;
    own_sum += row.own_wr;
    peer_sum += row.peer_wr_shared;
    Progress(absl::StrFormat(
        "[%s seed %d] %s: own area %d WR %.3f; peer's area %d WR %.3f shared "
        "vs %.3f alone (peer's own %.3f: %.0f%%)",
        spec.name, ctx.seed, row.robot, row.own_area, row.own_wr, row.peer_area,
        row.peer_wr_shared, row.peer_wr_alone, row.peer_own_wr,
        100 * row.peer_wr_shared / std::max(1e-9, row.peer_own_wr)));
  }
  result->summary.wr_final = wr_sum / 2;
  result->summary.ae = own_sum / 2;
  result->summary.ra = peer_sum / 2;
  return absl::OkStatus();
}

absl::StatusOr<MethodResult> RunFleetShared(Context& ctx,
                                            const MethodSpec& spec,
                                            std::vector<FleetRow>* rows,
                                            std::vector<WarmRow>* warm_rows) {
  MethodResult result;
  result.name = spec.name;
  result.seed = ctx.seed;
  const auto start = Clock::now();
  absl::StatusOr<std::unique_ptr<ServerChild>> server = StartServer(ctx, spec);
  if (!server.ok()) return server.status();
  std::unique_ptr<client::Client> client = Connect(**server);
  const int areas[2] = {0, 1};
  std::vector<Robot> shared, alone;
  for (int k = 0; k < 2; ++k) {
    for (std::vector<Robot>* group : {&shared, &alone}) {
      absl::StatusOr<Robot> r = NewRobot(
          ctx, spec, std::string("robot-") + char('a' + k), ctx.seed + 31 + k);
      if (!r.ok()) return r.status();
      group->push_back(*std::move(r));
    }
  }
  for (int season = 0; season < kSeasons; ++season) {
    std::vector<std::vector<size_t>> segs[2];
    for (int k = 0; k < 2; ++k) {
      segs[k] = Segments(ctx.data->split.Places(areas[k], false),
                         ctx.settings.segment_size);
    }
    for (size_t j = 0; j < std::max(segs[0].size(), segs[1].size()); ++j) {
      for (int k = 0; k < 2; ++k) {
        if (j >= segs[k].size()) continue;
        absl::Status s = RunSegment(ctx, spec, shared[k], season, segs[k][j],
                                    client.get(), "fleet-shared");
        if (!s.ok()) return s;
        s = RunSegment(ctx, spec, alone[k], season, segs[k][j], client.get(),
                       absl::StrCat("alone-", shared[k].id));
        if (!s.ok()) return s;
      }
    }
    Progress(absl::StrFormat(
        "[%s seed %d] %s done for both robots (and each alone) (%.0f s)",
        spec.name, ctx.seed, kSeasonNames[season], Seconds(start)));
  }
  absl::StatusOr<WarmRow> warm =
      RunWarmStart(ctx, spec, client.get(), "fleet-shared");
  if (!warm.ok()) return warm.status();
  warm_rows->push_back(*warm);
  if (absl::Status s = StopServer(**server); !s.ok()) return s;
  if (absl::Status scored =
          ScoreFleetShared(ctx, spec, areas, shared, alone, rows, &result);
      !scored.ok()) {
    return scored;
  }
  result.seconds = Seconds(start);
  return result;
}

// Mean and sample standard deviation.
std::pair<double, double> MeanSd(const std::vector<double>& v) {
  if (v.empty()) return {0, 0};
  double mean = 0;
  for (double x : v) mean += x;
  mean /= v.size();
  if (v.size() < 2) return {mean, 0};
  double ss = 0;
  for (double x : v) ss += (x - mean) * (x - mean);
  return {mean, std::sqrt(ss / (v.size() - 1))};
}

struct Aggregate {
  std::string name;
  std::string learner;
  int seeds = 0;
  std::pair<double, double> wr_final, ae, ra, unseen;
  double seconds = 0;
  int collapses = 0;  // over every seed's segments
  // Mean over seeds of areas[t][a].wr and of the mean over areas.
  std::vector<std::vector<double>> wr;
};

Aggregate AggregateSeeds(const MethodSpec& spec,
                         const std::vector<MethodResult>& runs) {
  Aggregate a;
  a.name = spec.name;
  a.learner = spec.learner == LearnerKind::kGpl      ? "gpl"
              : spec.learner == LearnerKind::kMetric ? "metric"
                                                     : "-";
  a.seeds = int(runs.size());
  std::vector<double> wr, ae, ra, unseen;
  for (const MethodResult& r : runs) {
    wr.push_back(r.summary.wr_final);
    ae.push_back(r.summary.ae);
    ra.push_back(r.summary.ra);
    unseen.push_back(r.summary.unseen);
    a.seconds += r.seconds;
    a.collapses += r.collapses;
  }
  a.wr_final = MeanSd(wr);
  a.ae = MeanSd(ae);
  a.ra = MeanSd(ra);
  a.unseen = MeanSd(unseen);
  if (!runs.empty() && !runs[0].areas.empty()) {
    a.wr.assign(kDomains, std::vector<double>(kAreas, 0.0));
    for (const MethodResult& r : runs)
      for (int t = 0; t < kDomains; ++t)
        for (int d = 0; d < kAreas; ++d)
          a.wr[t][d] += r.areas[t][d].wr / runs.size();
  }
  return a;
}

// curves.dat's block of one method, mean over seeds: after domain t, the
// mean WR over the three areas, the WR of the area just learned (winter
// domains) and the mean over the winter areas learned before.
std::string PlotBlock(const Aggregate& a) {
  std::string plot;
  for (int t = 0; t < kDomains; ++t) {
    double mean = 0;
    for (double w : a.wr[t]) mean += w / kAreas;
    const int w_area = t - kAreas;
    double earlier = 0;
    for (int d = 0; d < w_area; ++d) earlier += a.wr[t][d];
    plot += absl::StrFormat(
        "%d %.4f %s %s\n", t + 1, mean,
        w_area >= 0 ? absl::StrFormat("%.4f", a.wr[t][w_area]) : "NaN",
        w_area > 0 ? absl::StrFormat("%.4f", earlier / w_area) : "NaN");
  }
  return plot + "\n\n";
}

// fleet.csv: each robot of the fleet-shared runs, its own area and its
// peer's.
std::string FleetCsv(const std::vector<FleetRow>& fleet) {
  std::string csv =
      "method,seed,robot,own_area,own_wr,peer_area,peer_wr_shared,"
      "peer_wr_alone,peer_own_wr,ratio_to_peer\n";
  for (const FleetRow& f : fleet) {
    csv += absl::StrFormat(
        "%s,%d,%s,%d,%.4f,%d,%.4f,%.4f,%.4f,%.4f\n", f.method, f.seed, f.robot,
        f.own_area, f.own_wr, f.peer_area, f.peer_wr_shared, f.peer_wr_alone,
        f.peer_own_wr, f.peer_wr_shared / std::max(1e-9, f.peer_own_wr));
  }
  return csv;
}

// warm_start.csv: the new robot's WR on its peers' areas (RunWarmStart).
std::string WarmCsv(const std::vector<WarmRow>& rows) {
  std::string csv =
      "method,seed,hog,warm_start,warm_first_segment,cold_first_segment,"
      "alone_first_segment\n";
  for (const WarmRow& w : rows) {
    csv += absl::StrFormat("%s,%d,%.4f,%.4f,%.4f,%.4f,%.4f\n", w.method, w.seed,
                           w.hog, w.warm, w.warm_first_segment,
                           w.cold_first_segment, w.alone_first_segment);
  }
  return csv;
}

// curves.gp, and curves.png from curves.dat's `block` blocks (titled
// `plot_titles`) with gnuplot: three panels over the course of training
// (none without a block).
absl::Status DrawCurves(const std::string& dir, const std::string& plot_titles,
                        const std::string& data_root, int block) {
  const std::string script = absl::StrFormat(
      "set terminal pngcairo size 1500,480 font 'sans,10'\n"
      "set output '%s/curves.png'\n"
      "titles = '%s'\n"
      "set multiplot layout 1,3 title 'Lifelong place recognition on %s "
      "(protocol v2: winter queries of held-out places against the summer "
      "map; domains summer areas 1-3, then winter areas 1-3)'\n"
      "set termoption noenhanced\n"
      "set xrange [0.8:6.2]; set yrange [0:*]; set grid\n"
      "set key top left font ',8'\n"
      "set xtics ('S1' 1, 'S2' 2, 'S3' 3, 'W1' 4, 'W2' 5, 'W3' 6)\n"
      "set xlabel 'after learning domain'\n"
      "set title 'WR, mean over the three areas'\n"
      "plot for [i=0:%d] '%s/curves.dat' index i using 1:2 with linespoints "
      "title word(titles, i+1)\n"
      "set title 'AE: WR on the winter area just learned'\n"
      "plot for [i=0:%d] '%s/curves.dat' index i using 1:3 with linespoints "
      "title word(titles, i+1)\n"
      "set title 'RA: WR on the winter areas learned before'\n"
      "plot for [i=0:%d] '%s/curves.dat' index i using 1:4 with linespoints "
      "title word(titles, i+1)\n"
      "unset multiplot\n",
      dir, plot_titles, data_root, block - 1, dir, block - 1, dir, block - 1,
      dir);
  if (absl::Status s = files::WriteFile(dir + "/curves.gp", script); !s.ok())
    return s;
  const std::string command =
      absl::StrCat("gnuplot '", dir, "/curves.gp' 2>'", dir, "/gnuplot.log'");
  if (block > 0 && std::system(command.c_str()) != 0) {
    return absl::InternalError(absl::StrCat(
        "gnuplot failed to draw curves.png (the CSVs are written); see ", dir,
        "/gnuplot.log"));
  }
  return absl::OkStatus();
}

absl::Status WriteOutputs(
    const LifelongOptions& options, const Data& data,
    const std::vector<MethodSpec>& specs,
    const std::map<std::string, std::vector<MethodResult>>& results,
    const std::vector<FleetRow>& fleet, const std::vector<WarmRow>& warm,
    std::string* table_out) {
  const std::string& dir = options.out_dir;
  const Score chance = lifelong::ChanceScore(data.split);
  std::string summary =
      "method,learner,seeds,wr_final,wr_final_sd,ae,ae_sd,ra,ra_sd,unseen,"
      "unseen_sd,seconds,collapses\n";
  summary += absl::StrFormat("chance,-,0,%.4f,0,%.4f,0,%.4f,0,%.4f,0,0,0\n",
                             chance.wr, chance.wr, chance.wr, chance.wr);
  std::string table = absl::StrFormat(
      "| method | learner | seeds | WR final | AE | RA | WR on areas not yet "
      "learned | time (s) | collapsed segments |\n"
      "|---|---|---:|---:|---:|---:|---:|---:|---:|\n"
      "| chance | - | - | %.3f | %.3f | %.3f | %.3f | 0 | - |\n",
      chance.wr, chance.wr, chance.wr, chance.wr);
  std::string curves = "method,seed,after_domain,area,r1,r2,r3,r4,r5,r6,wr\n";
  std::string memory = "method,seed,peak_traces,final_traces\n";
  std::string plot, plot_titles;
  int block = 0;
  auto pm = [](const std::pair<double, double>& v, int seeds) {
    return seeds > 1 ? absl::StrFormat("%.3f ± %.3f", v.first, v.second)
                     : absl::StrFormat("%.3f", v.first);
  };
  for (const MethodSpec& spec : specs) {
    const auto it = results.find(spec.name);
    if (it == results.end()) continue;
    const Aggregate a = AggregateSeeds(spec, it->second);
    summary += absl::StrFormat(
        "%s,%s,%d,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.0f,%d\n", a.name,
        a.learner, a.seeds, a.wr_final.first, a.wr_final.second, a.ae.first,
        a.ae.second, a.ra.first, a.ra.second, a.unseen.first, a.unseen.second,
        a.seconds, a.collapses);
    table += absl::StrFormat(
        "| %s | %s | %d | %s | %s | %s | %s | %.0f | %d |\n", a.name, a.learner,
        a.seeds, pm(a.wr_final, a.seeds), pm(a.ae, a.seeds), pm(a.ra, a.seeds),
        a.wr.empty() ? "-" : pm(a.unseen, a.seeds), a.seconds, a.collapses);
    for (const MethodResult& r : it->second) {
      if (spec.memory != MemoryKind::kNone && !IsShared(spec)) {
        memory += absl::StrFormat("%s,%d,%d,%d\n", r.name, r.seed,
                                  r.peak_traces, r.final_traces);
      }
      for (size_t t = 0; t < r.areas.size(); ++t) {
        for (size_t d = 0; d < r.areas[t].size(); ++d) {
          const Score& s = r.areas[t][d];
          curves += absl::StrFormat(
              "%s,%d,%d,%d,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f\n", r.name,
              r.seed, t + 1, d + 1, s.recall[0], s.recall[1], s.recall[2],
              s.recall[3], s.recall[4], s.recall[5], s.wr);
        }
      }
    }
    if (a.wr.empty()) continue;
    plot += PlotBlock(a);
    plot_titles += absl::StrFormat("%s\"%s\"", block ? " " : "", a.name);
    ++block;
  }
  const std::string fleet_csv = FleetCsv(fleet);
  for (const auto& [name, text] :
       std::vector<std::pair<std::string, std::string>>{
           {"summary.csv", summary},
           {"summary.md", table},
           {"curves.csv", curves},
           {"curves.dat", plot},
           {"memory.csv", memory},
           {"fleet.csv", fleet_csv},
           {"warm_start.csv", WarmCsv(warm)}}) {
    if (absl::Status s = files::WriteFile(dir + "/" + name, text); !s.ok())
      return s;
  }
  *table_out = table;
  return DrawCurves(dir, plot_titles, options.data_root, block);
}

}  // namespace

std::vector<std::string> LifelongMethodNames() {
  std::vector<std::string> names;
  for (const MethodSpec& s : Specs()) names.push_back(s.name);
  return names;
}

namespace {

// The methods `options` selects, checked: known names, bioslam beside
// uniform_replay, the server binary for a memory method.
absl::StatusOr<std::vector<MethodSpec>> SelectedSpecs(
    const LifelongOptions& options) {
  const std::vector<std::string> names = LifelongMethodNames();
  for (const std::string& m : options.methods) {
    if (std::find(names.begin(), names.end(), m) == names.end()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "unknown method '", m, "'; methods: ", absl::StrJoin(names, ", ")));
    }
  }
  auto selected = [&](const std::string& name) {
    return options.methods.empty() ||
           std::find(options.methods.begin(), options.methods.end(), name) !=
               options.methods.end();
  };
  std::vector<MethodSpec> specs;
  for (const MethodSpec& s : Specs()) {
    if (selected(s.name)) specs.push_back(s);
  }
  if ((selected("uniform_replay") || selected("uniform_seq")) &&
      !selected("bioslam")) {
    return absl::InvalidArgumentError(
        "uniform_replay and uniform_seq keep as many traces as bioslam's "
        "memory holds, segment by segment: select bioslam too");
  }
  // A memory method needs the server: say so now, not after pre-training.
  if (std::any_of(
          specs.begin(), specs.end(),
          [](const MethodSpec& s) { return s.memory == MemoryKind::kFleet; }) &&
      ::access(options.server_binary.c_str(), X_OK) != 0) {
    return absl::NotFoundError(absl::StrCat("no fleetmem-server binary at ",
                                            options.server_binary,
                                            " (--server-binary)"));
  }
  return specs;
}

// The run's settings: the quick or full ones, with what `options` sets.
Settings SettingsOf(const LifelongOptions& options) {
  Settings settings = SettingsFor(options.quick);
  if (options.pretrain_steps > 0)
    settings.pretrain_steps = options.pretrain_steps;
  if (options.end_to_end_steps > 0)
    settings.end_to_end_steps = options.end_to_end_steps;
  if (options.steps_per_segment > 0)
    settings.steps_per_segment = options.steps_per_segment;
  if (options.seeds > 0) settings.seeds = options.seeds;
  return settings;
}

}  // namespace

absl::Status RunLifelong(const LifelongOptions& options) {
  absl::StatusOr<std::vector<MethodSpec>> selected = SelectedSpecs(options);
  if (!selected.ok()) return selected.status();
  const std::vector<MethodSpec>& specs = *selected;
  const bool any_gpl = std::any_of(
      specs.begin(), specs.end(),
      [](const MethodSpec& s) { return s.learner == LearnerKind::kGpl; });
  robot::gpl::SetTorchThreads(options.threads);
  const Settings settings = SettingsOf(options);
  const auto start = Clock::now();
  absl::StatusOr<Data> data =
      LoadData(options.data_root, options.skip_places, options.max_places);
  if (!data.ok()) return data.status();
  // The output folder only once the input is known to be good.
  std::error_code ec;
  std::filesystem::create_directories(options.out_dir, ec);
  if (ec) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot create ", options.out_dir, ": ", ec.message()));
  }
  const size_t queries = std::count(data->split.held_out.begin(),
                                    data->split.held_out.end(), true);
  Progress(absl::StrFormat(
      "[data] %s: %d places in both seasons (from file %d), 3 areas; map: the "
      "summer frame of every place; queries: the winter frames of %d held-out "
      "places; %s settings, %d seed(s)",
      options.data_root, data->numbers.size(), data->numbers.front(), queries,
      options.quick ? "quick" : "full", settings.seeds));
  std::map<std::string, std::vector<MethodResult>> results;
  std::vector<FleetRow> fleet;
  std::vector<WarmRow> warm;
  for (int k = 0; k < settings.seeds; ++k) {
    Context ctx;
    ctx.options = &options;
    ctx.settings = settings;
    ctx.data = &*data;
    ctx.seed = options.seed + uint64_t(k);
    ctx.server_binary = options.server_binary;
    if (options.negative_candidates > 0)
      ctx.mining.negative_candidates = options.negative_candidates;
    // Positives within +-2 files (the tolerance of a correct match),
    // negatives beyond 10 files.
    ctx.mining.positive_radius = lifelong::kTolerance * data->spacing;
    ctx.mining.negative_radius = 10 * data->spacing;
    absl::StatusOr<CodeSet> hog = HogCodes(*data, ctx.seed);
    if (!hog.ok()) return hog.status();
    ctx.hog = *std::move(hog);
    if (any_gpl) {
      if (absl::Status s = PretrainGpl(ctx); !s.ok()) return s;
    }
    for (const MethodSpec& spec : specs) {
      Progress(absl::StrFormat("[%s seed %d] start (%.0f s into the run)",
                               spec.name, ctx.seed, Seconds(start)));
      absl::StatusOr<MethodResult> r =
          IsShared(spec) ? RunFleetShared(ctx, spec, &fleet, &warm)
                         : RunSingleRobot(ctx, spec);
      if (!r.ok()) {
        return absl::Status(r.status().code(),
                            absl::StrCat("method ", spec.name, ", seed ",
                                         ctx.seed, ": ", r.status().message()));
      }
      Progress(absl::StrFormat(
          "[%s seed %d] WR final %.3f, AE %.3f, RA %.3f (%.0f s)", r->name,
          ctx.seed, r->summary.wr_final, r->summary.ae, r->summary.ra,
          r->seconds));
      results[spec.name].push_back(*std::move(r));
    }
  }
  std::string table;
  if (absl::Status s =
          WriteOutputs(options, *data, specs, results, fleet, warm, &table);
      !s.ok()) {
    return s;
  }
  std::printf(
      "\n%s\nwritten: %s/{summary.csv,summary.md,curves.csv,curves.png,"
      "memory.csv,fleet.csv} (%.0f s)\n",
      table.c_str(), options.out_dir.c_str(), Seconds(start));
  return absl::OkStatus();
}

}  // namespace fleetmem::eval
