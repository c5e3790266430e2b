#include "tools/eval/lifelong.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "Eigen/Dense"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/dynamic_memory.h"
#include "clients/robot/encoder.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/learning/pretrain.h"
#include "clients/robot/learning/segment_learner.h"
#include "clients/robot/nordland.h"
#include "clients/robot/rewards.h"
#include "opencv2/imgproc.hpp"
#include "proto/convert/trace_convert.h"
#include "services/common/files.h"
#include "services/core/place_metrics.h"
#include "tools/process/server_process.h"

namespace fleetmem::eval {
namespace {

using robot::gpl::GplModel;
using robot::gpl::LearnSample;
using robot::gpl::ReplayInput;
using robot::gpl::SegmentLearner;
using Clock = std::chrono::steady_clock;
using ServerChild = process::ServerProcess;

constexpr int kAreas = 3;
constexpr int kDomains = 2 * kAreas;
constexpr int kSeasons = 2;
constexpr const char* kSeasonNames[kSeasons] = {"summer", "winter"};
constexpr int kMaxK = 6;

// Step budgets, sized for 2 CPU cores (docs/results.md gives the costs).
struct Settings {
  int pretrain_steps;
  int steps_per_segment;
  int generative_steps;
  int batch_size = 32;
  size_t segment_size = 200;
  size_t replay_per_segment = 128;
  size_t memory_capacity = 1000;
};

Settings SettingsFor(bool quick) {
  if (quick)
    return Settings{
        .pretrain_steps = 300, .steps_per_segment = 40, .generative_steps = 2};
  return Settings{
      .pretrain_steps = 300, .steps_per_segment = 100, .generative_steps = 10};
}

std::string DomainName(int d) {
  return absl::StrCat(kSeasonNames[d / kAreas], " area ", d % kAreas + 1);
}

// The route: frames present in both seasons, in file order.
struct Data {
  std::vector<int> numbers;
  std::vector<cv::Mat> images[kSeasons];
  std::vector<int> area;
  std::vector<bool> query;
  double spacing = 10.0;  // place units between consecutive files

  core::Place PlaceOf(size_t i) const {
    core::Place p;
    p.x = numbers[i];
    return p;
  }
  std::vector<size_t> Indices(int area_id, bool queries) const {
    std::vector<size_t> out;
    for (size_t i = 0; i < numbers.size(); ++i) {
      if (area[i] == area_id && query[i] == queries) out.push_back(i);
    }
    return out;
  }
};

absl::StatusOr<Data> LoadData(const std::string& root, int max_places) {
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
  if (max_places > 0 && data.numbers.size() > size_t(max_places)) {
    data.numbers.resize(max_places);
  }
  if (data.numbers.size() < 8 * kAreas) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s/nordland: %d frames are present in both summer and winter; the "
        "protocol needs at least %d",
        root, data.numbers.size(), 8 * kAreas));
  }
  for (int s = 0; s < kSeasons; ++s) {
    const std::string dir = absl::StrCat(root, "/nordland/", kSeasonNames[s]);
    for (int number : data.numbers) {
      absl::StatusOr<cv::Mat> image = robot::LoadNordlandGrey(dir, number);
      if (!image.ok()) return image.status();
      data.images[s].push_back(*std::move(image));
    }
  }
  const size_t n = data.numbers.size();
  std::vector<int> gaps;
  for (size_t i = 0; i < n; ++i) {
    data.area.push_back(int(i * kAreas / n));
    data.query.push_back(i % 4 == 3);
    if (i > 0) gaps.push_back(data.numbers[i] - data.numbers[i - 1]);
  }
  std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2, gaps.end());
  data.spacing = std::max(1, gaps[gaps.size() / 2]);
  return data;
}

// Unit rows for cosine search.
Eigen::MatrixXf Normalised(const std::vector<std::vector<float>>& rows,
                           const std::vector<size_t>& pick) {
  const size_t dim = rows.empty() ? 0 : rows[0].size();
  Eigen::MatrixXf m(pick.size(), dim);
  for (size_t r = 0; r < pick.size(); ++r) {
    const std::vector<float>& v = rows[pick[r]];
    for (size_t c = 0; c < dim; ++c) m(r, c) = v[c];
    const float norm = m.row(r).norm();
    if (norm > 0) m.row(r) /= norm;
  }
  return m;
}

struct DomainScore {
  double recall[kMaxK] = {};
  double wr = 0.0;
};

// Recall@1..6 and WR of every domain's queries against the summer training
// frames; descriptors[s][i] for season s and route index i.
std::vector<DomainScore> Evaluate(
    const Data& data,
    const std::vector<std::vector<float>> (&descriptors)[kSeasons]) {
  std::vector<size_t> db;
  for (int a = 0; a < kAreas; ++a) {
    for (size_t i : data.Indices(a, false)) db.push_back(i);
  }
  const Eigen::MatrixXf database = Normalised(descriptors[0], db);
  std::vector<DomainScore> scores(kDomains);
  for (int d = 0; d < kDomains; ++d) {
    const std::vector<size_t> queries = data.Indices(d % kAreas, true);
    const Eigen::MatrixXf q = Normalised(descriptors[d / kAreas], queries);
    const Eigen::MatrixXf sim = q * database.transpose();
    core::FirstCorrectRanks ranks;
    std::vector<int> order(db.size());
    for (size_t r = 0; r < queries.size(); ++r) {
      for (size_t j = 0; j < db.size(); ++j) order[j] = int(j);
      const size_t k = std::min<size_t>(kMaxK, db.size());
      std::partial_sort(
          order.begin(), order.begin() + k, order.end(), [&](int a, int b) {
            return sim(r, a) > sim(r, b) || (sim(r, a) == sim(r, b) && a < b);
          });
      int first = 0;
      for (size_t j = 0; j < k && first == 0; ++j) {
        const long gap = long(db[order[j]]) - long(queries[r]);
        if (std::abs(gap) <= 2) first = int(j) + 1;  // within +-2 files
      }
      ranks.push_back(first);
    }
    for (int k = 1; k <= kMaxK; ++k)
      scores[d].recall[k - 1] = core::RecallAtK(ranks, k);
    scores[d].wr = core::WeightedRecall(ranks);
  }
  return scores;
}

// What one method reports.
struct MethodResult {
  std::string name;
  // scores[t][d]: after learning domain t, WR etc. of domain d.
  std::vector<std::vector<DomainScore>> scores;
  double wr_final = 0, ae = 0, ra = 0, generalisation = 0;
  double seconds = 0;

  void Summarise() {
    const size_t t_end = scores.size();
    if (t_end == 0) return;
    double sum = 0;
    for (const DomainScore& s : scores.back()) sum += s.wr;
    wr_final = sum / scores.back().size();
    double ae_sum = 0, ra_sum = 0, gen_sum = 0;
    int ra_n = 0, gen_n = 0;
    for (size_t t = 0; t < t_end; ++t) {
      ae_sum += scores[t][t].wr;
      if (t > 0) {
        double earlier = 0;
        for (size_t d = 0; d < t; ++d) earlier += scores[t][d].wr;
        ra_sum += earlier / t;
        ++ra_n;
      }
      if (t + 1 < scores[t].size()) {
        double later = 0;
        for (size_t d = t + 1; d < scores[t].size(); ++d)
          later += scores[t][d].wr;
        gen_sum += later / (scores[t].size() - t - 1);
        ++gen_n;
      }
    }
    ae = ae_sum / t_end;
    ra = ra_n ? ra_sum / ra_n : 0;
    generalisation = gen_n ? gen_sum / gen_n : 0;
  }
};

enum class RewardMode { kFull, kNoExternal, kNoInternal, kUniform };

struct MethodSpec {
  std::string name;
  bool learn = true;
  bool remember = false;  // a fleet memory on the server, replay from M_D
  bool clustering = true;
  bool decay = true;
  RewardMode rewards = RewardMode::kFull;
  ReplayInput replay_input = ReplayInput::kCode;
};

std::vector<MethodSpec> Specs() {
  std::vector<MethodSpec> specs;
  specs.push_back({.name = "classical", .learn = false});
  specs.push_back({.name = "gpl_pretrained", .learn = false});
  specs.push_back({.name = "finetune"});
  specs.push_back({.name = "uniform_replay",
                   .remember = true,
                   .clustering = false,
                   .decay = false,
                   .rewards = RewardMode::kUniform});
  specs.push_back({.name = "bioslam", .remember = true});
  specs.push_back(
      {.name = "no_rex", .remember = true, .rewards = RewardMode::kNoExternal});
  specs.push_back(
      {.name = "no_rin", .remember = true, .rewards = RewardMode::kNoInternal});
  specs.push_back(
      {.name = "no_clustering", .remember = true, .clustering = false});
  specs.push_back({.name = "no_decay", .remember = true, .decay = false});
  specs.push_back({.name = "bioslam_decoded",
                   .remember = true,
                   .replay_input = ReplayInput::kDecoded});
  specs.push_back({.name = "fleet_shared", .remember = true});
  return specs;
}

void Progress(const std::string& line) {
  std::fprintf(stderr, "%s\n", line.c_str());
  std::fflush(stderr);
}

// Everything the methods share: the data, the pre-trained fleet encoder,
// every frame's code and R_in, the settings.
struct Context {
  const LifelongOptions* options;
  Settings settings;
  Data data;
  std::unique_ptr<GplModel> pretrained;
  std::vector<std::vector<float>> codes[kSeasons];
  std::vector<float> internal[kSeasons];
  robot::gpl::TripletMiningOptions mining;
  // Traces recalled from the fleet memory per new observation (0 = none).
  uint32_t recall_per_observation = 4;
  std::string server_binary;
  std::string config_file[2][2];  // [clustering][decay]
};

absl::StatusOr<std::vector<std::vector<float>>> DescribeAll(
    GplModel& model, const std::vector<std::vector<float>>& codes) {
  std::vector<std::vector<float>> out;
  for (size_t begin = 0; begin < codes.size(); begin += 1024) {
    const size_t end = std::min(codes.size(), begin + 1024);
    absl::StatusOr<std::vector<std::vector<float>>> d = model.Describe(
        std::span<const std::vector<float>>(codes.data() + begin, end - begin));
    if (!d.ok()) return d.status();
    for (auto& row : *d) out.push_back(std::move(row));
  }
  return out;
}

absl::StatusOr<std::vector<DomainScore>> EvaluateModel(Context& ctx,
                                                       GplModel& model) {
  std::vector<std::vector<float>> descriptors[kSeasons];
  for (int s = 0; s < kSeasons; ++s) {
    absl::StatusOr<std::vector<std::vector<float>>> d =
        DescribeAll(model, ctx.codes[s]);
    if (!d.ok()) return d.status();
    descriptors[s] = *std::move(d);
  }
  return Evaluate(ctx.data, descriptors);
}

// Pre-training of the fleet encoder (learning.md: trained once on the
// initial domain, then frozen): L_joint (Eq. 10) on summer area 1's
// training frames, then every frame is encoded once.
absl::Status Pretrain(Context& ctx) {
  const Data& data = ctx.data;
  robot::gpl::PretrainOptions options;
  options.model.seed = ctx.options->seed;
  options.model.code_dimension = ctx.options->code_dimension;
  if (ctx.options->head_learning_rate > 0) {
    options.model.head_learning_rate = ctx.options->head_learning_rate;
  }
  if (ctx.options->gan_weight >= 0)
    options.model.gan_weight = float(ctx.options->gan_weight);
  options.version =
      absl::StrFormat("gpl-64x32-d%d-s%d-p%d-v1", options.model.code_dimension,
                      ctx.options->seed, ctx.settings.pretrain_steps);
  options.steps = ctx.settings.pretrain_steps;
  options.batch_size = ctx.settings.batch_size / 2;
  options.positive_radius = ctx.mining.positive_radius;
  options.negative_radius = ctx.mining.negative_radius;
  options.seed = ctx.options->seed;
  options.log = [](std::string_view line) { Progress(std::string(line)); };
  std::vector<cv::Mat> images;
  std::vector<double> positions;
  for (size_t i : data.Indices(0, false)) {
    images.push_back(data.images[0][i]);
    positions.push_back(data.numbers[i]);
  }
  const auto start = Clock::now();
  absl::StatusOr<std::unique_ptr<GplModel>> model =
      robot::gpl::PretrainFleetEncoder(images, positions, options);
  if (!model.ok()) return model.status();
  std::mt19937_64 rng(ctx.options->seed);
  ctx.pretrained = *std::move(model);
  if (absl::Status s =
          ctx.pretrained->Save(ctx.options->out_dir + "/encoder.pt");
      !s.ok()) {
    return s;
  }
  // Codes and R_in (Eq. 12, A = a random shift-crop) of every frame.
  for (int s = 0; s < kSeasons; ++s) {
    absl::StatusOr<std::vector<std::vector<float>>> z =
        ctx.pretrained->Encode(data.images[s]);
    if (!z.ok()) return z.status();
    ctx.codes[s] = *std::move(z);
    std::vector<cv::Mat> moved;
    for (const cv::Mat& image : data.images[s]) {
      absl::StatusOr<cv::Mat> m = robot::RandomShiftCrop(image, {}, rng);
      if (!m.ok()) return m.status();
      moved.push_back(*std::move(m));
    }
    absl::StatusOr<std::vector<std::vector<float>>> zm =
        ctx.pretrained->Encode(moved);
    if (!zm.ok()) return zm.status();
    for (size_t i = 0; i < moved.size(); ++i) {
      ctx.internal[s].push_back(
          robot::InternalReward(ctx.codes[s][i], (*zm)[i]));
    }
  }
  Progress(absl::StrFormat(
      "[pretrain] fleet encoder %s frozen: %d parameters, %.0f s",
      ctx.pretrained->version(), ctx.pretrained->ParameterCount(),
      std::chrono::duration<double>(Clock::now() - start).count()));
  return absl::OkStatus();
}

// One robot of a method: its model, learner and dynamic memory.
struct Robot {
  std::string id;
  std::unique_ptr<GplModel> model;
  std::unique_ptr<SegmentLearner> learner;
  std::unique_ptr<robot::DynamicMemory> memory;
  uint64_t next_seq = 1;
  std::mt19937_64 rng;
  robot::gpl::SegmentLearnStats last;
};

absl::StatusOr<Robot> NewRobot(Context& ctx, const MethodSpec& spec,
                               const std::string& id, uint64_t seed) {
  Robot r;
  r.id = id;
  absl::StatusOr<std::unique_ptr<GplModel>> model = ctx.pretrained->Clone();
  if (!model.ok()) return model.status();
  r.model = *std::move(model);
  robot::gpl::SegmentLearnerOptions lo;
  lo.steps_per_segment = ctx.settings.steps_per_segment;
  lo.batch_size = ctx.settings.batch_size;
  lo.replay_input = spec.replay_input;
  lo.generative_steps_per_segment = spec.replay_input == ReplayInput::kDecoded
                                        ? ctx.settings.generative_steps
                                        : 0;
  lo.mining = ctx.mining;
  lo.seed = seed;
  r.learner = std::make_unique<SegmentLearner>(r.model.get(), lo);
  robot::DynamicMemoryOptions mo;
  mo.capacity = ctx.settings.memory_capacity;
  mo.gamma = spec.decay ? 0.9 : 1.0;
  r.memory = std::make_unique<robot::DynamicMemory>(id, mo);
  r.rng.seed(seed);
  return r;
}

LearnSample FromTrace(const core::MemoryTrace& t) {
  return {t.code, t.place, t.domain == kSeasonNames[1] ? 1 : 0};
}

// Algorithm 3 for one segment of one robot: replay and learn, rewards,
// upload and consolidate, refresh M_D.
absl::Status RunSegment(Context& ctx, const MethodSpec& spec, Robot& r,
                        int season, const std::vector<size_t>& segment,
                        client::Client* client, const std::string& fleet) {
  std::vector<LearnSample> real;
  for (size_t i : segment)
    real.push_back({ctx.codes[season][i], ctx.data.PlaceOf(i), season});
  std::vector<LearnSample> memory;
  for (const robot::ReplayEntry& e : r.memory->entries())
    memory.push_back(FromTrace(e.trace));
  if (spec.learn && spec.remember && ctx.recall_per_observation > 0) {
    // Place recall: the fleet's remembered traces of each new observation's
    // place (QueryPlace with a position prior), the partners of Eq. 7.
    std::set<std::pair<std::string, uint64_t>> seen;
    for (const LearnSample& x : real) {
      v1::QueryPlaceRequest request;
      request.set_fleet_id(fleet);
      request.mutable_code()->Add(x.code.begin(), x.code.end());
      request.set_k(ctx.recall_per_observation);
      api::PlaceToProto(x.place, request.mutable_near());
      request.set_radius_m(ctx.mining.positive_radius);
      absl::StatusOr<std::vector<v1::PlaceMatch>> matches =
          client->QueryPlace(request);
      if (absl::IsNotFound(matches.status())) break;  // no fleet memory yet
      if (!matches.ok()) return matches.status();
      for (const v1::PlaceMatch& m : *matches) {
        if (seen.insert({m.trace().robot_id(), m.trace().seq()}).second) {
          memory.push_back(FromTrace(api::TraceFromProto(m.trace())));
        }
      }
    }
  }
  if (spec.learn) {
    std::vector<LearnSample> replayed;
    if (spec.remember) {
      for (const core::MemoryTrace& t :
           r.memory->Replay(ctx.settings.replay_per_segment, r.rng)) {
        replayed.push_back(FromTrace(t));
      }
    }
    absl::StatusOr<robot::gpl::SegmentLearnStats> stats =
        r.learner->Learn(real, replayed, memory);
    if (!stats.ok()) return stats.status();
    r.last = *stats;
    if (spec.replay_input == ReplayInput::kDecoded) {
      std::vector<cv::Mat> images;
      for (size_t i : segment) images.push_back(ctx.data.images[season][i]);
      if (absl::Status s = r.learner->LearnImages(images); !s.ok()) return s;
    }
  }
  if (!spec.remember) return absl::OkStatus();
  absl::StatusOr<std::vector<float>> external =
      r.learner->ExternalRewards(real, memory);
  if (!external.ok()) return external.status();
  std::vector<v1::MemoryTrace> traces;
  std::vector<core::MemoryTrace> own;
  for (size_t k = 0; k < segment.size(); ++k) {
    core::MemoryTrace t;
    t.robot_id = r.id;
    t.seq = r.next_seq++;
    t.domain = kSeasonNames[season];
    t.code = real[k].code;
    t.place = real[k].place;
    t.reward_external = (*external)[k];
    t.reward_internal = ctx.internal[season][segment[k]];
    switch (spec.rewards) {
      case RewardMode::kFull:
        t.reward = t.reward_external + t.reward_internal;
        break;
      case RewardMode::kNoExternal:
        t.reward = t.reward_internal;
        break;
      case RewardMode::kNoInternal:
        t.reward = t.reward_external;
        break;
      case RewardMode::kUniform:
        t.reward = 1.0f;
        break;
    }
    t.timestamp_ns = int64_t(t.seq);
    t.encoder_version = r.model->version();
    own.push_back(t);
    api::TraceToProto(t, &traces.emplace_back());
  }
  absl::StatusOr<v1::UploadTracesResponse> uploaded =
      client->Upload(fleet, traces);
  if (!uploaded.ok()) return uploaded.status();
  absl::StatusOr<v1::ConsolidateResponse> consolidated =
      client->Consolidate(fleet);
  if (!consolidated.ok()) return consolidated.status();
  for (const core::MemoryTrace& t : own) r.memory->AddOwn(t);
  absl::StatusOr<std::vector<v1::MemoryTrace>> sampled =
      client->SampleReplay(fleet, r.id, uint32_t(ctx.settings.memory_capacity));
  if (!sampled.ok()) return sampled.status();
  std::vector<core::MemoryTrace> refreshed;
  for (const v1::MemoryTrace& t : *sampled)
    refreshed.push_back(api::TraceFromProto(t));
  r.memory->Refresh(refreshed);
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

// A server child with the method's memory configuration.
absl::StatusOr<std::unique_ptr<ServerChild>> StartServer(
    Context& ctx, const MethodSpec& spec) {
  const std::string dir =
      absl::StrCat(ctx.options->out_dir, "/servers/", spec.name);
  std::error_code ec;
  std::filesystem::remove_all(dir, ec);
  std::filesystem::create_directories(dir + "/data", ec);
  if (ec)
    return absl::InternalError(
        absl::StrCat("cannot create ", dir, ": ", ec.message()));
  process::ServerOptions options;
  options.binary = ctx.server_binary;
  options.data_dir = dir + "/data";
  options.config_file = ctx.config_file[spec.clustering][spec.decay];
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
    return absl::InternalError(absl::StrCat(
        "the server exited with ", *code, " on SIGTERM; its log: ",
        server.options().log_file));
  }
  return absl::OkStatus();
}

std::unique_ptr<client::Client> Connect(const ServerChild& server) {
  client::ClientOptions o;
  o.target = server.address();
  o.deadline = std::chrono::milliseconds(60000);
  return client::Client::Create(o);
}

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

double SeenWr(const std::vector<DomainScore>& scores, size_t t) {
  double sum = 0;
  for (size_t d = 0; d <= t; ++d) sum += scores[d].wr;
  return sum / (t + 1);
}

absl::StatusOr<MethodResult> RunSingleRobot(Context& ctx,
                                            const MethodSpec& spec) {
  MethodResult result;
  result.name = spec.name;
  const auto start = Clock::now();
  if (spec.name == "classical") {
    absl::StatusOr<std::unique_ptr<robot::Encoder>> hog =
        robot::NewEncoderByName("hog-64x32-c8-s8-b6");
    if (!hog.ok()) return hog.status();
    std::vector<std::vector<float>> codes[kSeasons];
    for (int s = 0; s < kSeasons; ++s) {
      for (const cv::Mat& image : ctx.data.images[s]) {
        robot::Observation o;
        o.image = image;
        absl::StatusOr<std::vector<float>> z = (*hog)->Encode(o);
        if (!z.ok()) return z.status();
        codes[s].push_back(*std::move(z));
      }
    }
    const std::vector<DomainScore> scores = Evaluate(ctx.data, codes);
    result.scores.assign(
        kDomains, scores);  // nothing learns: the same after every domain
    result.Summarise();
    result.seconds = Seconds(start);
    return result;
  }
  std::unique_ptr<ServerChild> server;
  std::unique_ptr<client::Client> client;
  if (spec.remember) {
    absl::StatusOr<std::unique_ptr<ServerChild>> s = StartServer(ctx, spec);
    if (!s.ok()) return s.status();
    server = *std::move(s);
    client = Connect(*server);
  }
  absl::StatusOr<Robot> robot =
      NewRobot(ctx, spec, "robot-1", ctx.options->seed + 17);
  if (!robot.ok()) return robot.status();
  for (int t = 0; t < kDomains; ++t) {
    const int season = t / kAreas;
    const auto segments = Segments(ctx.data.Indices(t % kAreas, false),
                                   ctx.settings.segment_size);
    if (spec.learn) {
      for (const auto& segment : segments) {
        absl::Status s = RunSegment(ctx, spec, *robot, season, segment,
                                    client.get(), spec.name);
        if (!s.ok()) return s;
      }
    }
    absl::StatusOr<std::vector<DomainScore>> scores =
        EvaluateModel(ctx, *robot->model);
    if (!scores.ok()) return scores.status();
    result.scores.push_back(*scores);
    const auto counts = robot->memory->CountByRobot();
    Progress(absl::StrFormat(
        "[%s] domain %d/%d (%s): %d segments, last loss %.3f -> %.3f, M_D %d, "
        "WR "
        "here %.3f, seen %.3f (%.0f s)",
        spec.name, t + 1, kDomains, DomainName(t), segments.size(),
        robot->last.first_loss, robot->last.last_loss, robot->memory->size(),
        (*scores)[t].wr, SeenWr(*scores, t), Seconds(start)));
  }
  if (server) {
    if (absl::Status s = StopServer(*server); !s.ok()) return s;
  }
  result.Summarise();
  result.seconds = Seconds(start);
  return result;
}

// fleet_shared: robot A drives area 1, robot B area 2, summer then winter,
// segments interleaved, through one fleet memory; each is compared with
// itself driving alone (a fleet of its own) on the area only the peer drove.
struct FleetRow {
  std::string robot;
  int own_area = 0, peer_area = 0;
  double own_wr = 0, peer_wr_shared = 0, peer_wr_alone = 0, peer_own_wr = 0;
  double peer_winter_shared = 0, peer_winter_alone = 0,
         peer_winter_peer_own = 0;
};

absl::StatusOr<MethodResult> RunFleetShared(Context& ctx,
                                            const MethodSpec& spec,
                                            std::vector<FleetRow>* rows) {
  MethodResult result;
  result.name = spec.name;
  const auto start = Clock::now();
  absl::StatusOr<std::unique_ptr<ServerChild>> server = StartServer(ctx, spec);
  if (!server.ok()) return server.status();
  std::unique_ptr<client::Client> client = Connect(**server);
  const int areas[2] = {0, 1};
  std::vector<Robot> shared, alone;
  for (int k = 0; k < 2; ++k) {
    absl::StatusOr<Robot> a =
        NewRobot(ctx, spec, std::string("robot-") + char('a' + k),
                 ctx.options->seed + 31 + k);
    absl::StatusOr<Robot> b =
        NewRobot(ctx, spec, std::string("robot-") + char('a' + k),
                 ctx.options->seed + 31 + k);
    if (!a.ok()) return a.status();
    if (!b.ok()) return b.status();
    shared.push_back(*std::move(a));
    alone.push_back(*std::move(b));
  }
  for (int season = 0; season < kSeasons; ++season) {
    std::vector<std::vector<size_t>> segs[2];
    for (int k = 0; k < 2; ++k) {
      segs[k] = Segments(ctx.data.Indices(areas[k], false),
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
        "[%s] %s done for both robots (and each alone) (%.0f s)", spec.name,
        kSeasonNames[season], Seconds(start)));
  }
  if (absl::Status s = StopServer(**server); !s.ok()) return s;
  std::vector<DomainScore> s_shared[2], s_alone[2];
  for (int k = 0; k < 2; ++k) {
    absl::StatusOr<std::vector<DomainScore>> a =
        EvaluateModel(ctx, *shared[k].model);
    absl::StatusOr<std::vector<DomainScore>> b =
        EvaluateModel(ctx, *alone[k].model);
    if (!a.ok()) return a.status();
    if (!b.ok()) return b.status();
    s_shared[k] = *a;
    s_alone[k] = *b;
  }
  auto area_wr = [](const std::vector<DomainScore>& s, int area) {
    return (s[area].wr + s[kAreas + area].wr) / 2;
  };
  double wr_sum = 0, own_sum = 0, peer_sum = 0;
  for (int k = 0; k < 2; ++k) {
    const int p = 1 - k;
    FleetRow row;
    row.robot = shared[k].id;
    row.own_area = areas[k] + 1;
    row.peer_area = areas[p] + 1;
    row.own_wr = area_wr(s_shared[k], areas[k]);
    row.peer_wr_shared = area_wr(s_shared[k], areas[p]);
    row.peer_wr_alone = area_wr(s_alone[k], areas[p]);
    row.peer_own_wr = area_wr(s_shared[p], areas[p]);
    row.peer_winter_shared = s_shared[k][kAreas + areas[p]].wr;
    row.peer_winter_alone = s_alone[k][kAreas + areas[p]].wr;
    row.peer_winter_peer_own = s_shared[p][kAreas + areas[p]].wr;
    rows->push_back(row);
    wr_sum += (row.own_wr + row.peer_wr_shared) / 2;
    own_sum += row.own_wr;
    peer_sum += row.peer_wr_shared;
    Progress(absl::StrFormat(
        "[%s] %s: own area %d WR %.3f; peer's area %d WR %.3f shared vs %.3f "
        "alone "
        "(peer's own %.3f: %.0f%%)",
        spec.name, row.robot, row.own_area, row.own_wr, row.peer_area,
        row.peer_wr_shared, row.peer_wr_alone, row.peer_own_wr,
        100 * row.peer_wr_shared / std::max(1e-9, row.peer_own_wr)));
  }
  result.wr_final = wr_sum / 2;
  result.ae = own_sum / 2;
  result.ra = peer_sum / 2;
  result.seconds = Seconds(start);
  return result;
}

absl::Status WriteConfigs(Context& ctx) {
  for (int clustering = 0; clustering < 2; ++clustering) {
    for (int decay = 0; decay < 2; ++decay) {
      const std::string path =
          absl::StrFormat("%s/server-c%d-d%d.textproto", ctx.options->out_dir,
                          clustering, decay);
      absl::Status s = files::WriteFile(
          path,
          absl::StrFormat("log_level: \"warning\"\nmemory {\n  clustering: %s\n"
                          "  replay_decay: %s\n  seed: %d\n}\n",
                          clustering ? "true" : "false", decay ? "0.9" : "1",
                          ctx.options->seed));
      if (!s.ok()) return s;
      ctx.config_file[clustering][decay] = path;
    }
  }
  return absl::OkStatus();
}

absl::Status WriteOutputs(const Context& ctx,
                          const std::vector<MethodResult>& results,
                          const std::vector<FleetRow>& fleet) {
  const std::string& dir = ctx.options->out_dir;
  std::string summary = "method,wr_final,ae,ra\n";
  std::string table =
      "| method | WR final | AE | RA | WR on domains not yet learned | time "
      "(s) |\n"
      "|---|---:|---:|---:|---:|---:|\n";
  std::string curves = "method,after_domain,domain,r1,r2,r3,r4,r5,r6,wr\n";
  std::string plot;
  int block = 0;
  std::string plot_titles;
  for (const MethodResult& r : results) {
    summary +=
        absl::StrFormat("%s,%.4f,%.4f,%.4f\n", r.name, r.wr_final, r.ae, r.ra);
    table += absl::StrFormat(
        "| %s | %.3f | %.3f | %.3f | %s | %.0f |\n", r.name, r.wr_final, r.ae,
        r.ra,
        r.scores.empty() ? "-" : absl::StrFormat("%.3f", r.generalisation),
        r.seconds);
    if (r.scores.empty()) continue;
    for (size_t t = 0; t < r.scores.size(); ++t) {
      for (size_t d = 0; d < r.scores[t].size(); ++d) {
        const DomainScore& s = r.scores[t][d];
        curves += absl::StrFormat(
            "%s,%d,%d,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f\n", r.name, t + 1,
            d + 1, s.recall[0], s.recall[1], s.recall[2], s.recall[3],
            s.recall[4], s.recall[5], s.wr);
      }
    }
    // Plot data: after domain t, WR of each domain (learned or not), the
    // mean over learned domains, and the mean over earlier ones.
    for (size_t t = 0; t < r.scores.size(); ++t) {
      double earlier = 0;
      for (size_t d = 0; d < t; ++d) earlier += r.scores[t][d].wr;
      plot += absl::StrFormat(
          "%d %.4f %.4f %s", t + 1, SeenWr(r.scores[t], t), r.scores[t][t].wr,
          t == 0 ? "NaN" : absl::StrFormat("%.4f", earlier / t));
      for (size_t d = 0; d < r.scores[t].size(); ++d) {
        plot += absl::StrFormat(" %.4f", r.scores[t][d].wr);
      }
      plot += "\n";
    }
    plot += "\n\n";
    plot_titles += absl::StrFormat("%s\"%s\"", block ? " " : "", r.name);
    ++block;
  }
  std::string fleet_csv =
      "robot,own_area,own_wr,peer_area,peer_wr_shared,peer_wr_alone,peer_own_"
      "wr,"
      "ratio_to_peer,peer_winter_wr_shared,peer_winter_wr_alone,peer_winter_"
      "own_wr\n";
  for (const FleetRow& f : fleet) {
    fleet_csv += absl::StrFormat(
        "%s,%d,%.4f,%d,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f\n", f.robot,
        f.own_area, f.own_wr, f.peer_area, f.peer_wr_shared, f.peer_wr_alone,
        f.peer_own_wr, f.peer_wr_shared / std::max(1e-9, f.peer_own_wr),
        f.peer_winter_shared, f.peer_winter_alone, f.peer_winter_peer_own);
  }
  for (const auto& [name, text] :
       std::vector<std::pair<std::string, std::string>>{
           {"summary.csv", summary},
           {"summary.md", table},
           {"curves.csv", curves},
           {"curves.dat", plot},
           {"fleet.csv", fleet_csv}}) {
    if (absl::Status s = files::WriteFile(dir + "/" + name, text); !s.ok()) return s;
  }
  // curves.png with gnuplot: three panels over the course of training.
  const std::string script = absl::StrFormat(
      "set terminal pngcairo size 1500,480 font 'sans,10'\n"
      "set output '%s/curves.png'\n"
      "titles = '%s'\n"
      "set multiplot layout 1,3 title 'Lifelong place recognition on %s (WR, "
      "Nordland "
      "protocol: summer areas 1-3, then winter areas 1-3)'\n"
      "set termoption noenhanced\n"
      "set xrange [0.8:6.2]; set yrange [0:*]; set grid\n"
      "set key top right font ',8'\n"
      "set xtics ('S1' 1, 'S2' 2, 'S3' 3, 'W1' 4, 'W2' 5, 'W3' 6)\n"
      "set xlabel 'after learning domain'\n"
      "set title 'WR over the domains learned so far'\n"
      "plot for [i=0:%d] '%s/curves.dat' index i using 1:2 with linespoints "
      "title word(titles, i+1)\n"
      "set title 'AE: WR on the domain just learned'\n"
      "plot for [i=0:%d] '%s/curves.dat' index i using 1:3 with linespoints "
      "title word(titles, i+1)\n"
      "set title 'RA: WR on the earlier domains'\n"
      "plot for [i=0:%d] '%s/curves.dat' index i using 1:4 with linespoints "
      "title word(titles, i+1)\n"
      "unset multiplot\n",
      dir, plot_titles, ctx.options->data_root, block - 1, dir, block - 1, dir,
      block - 1, dir);
  if (absl::Status s = files::WriteFile(dir + "/curves.gp", script); !s.ok()) return s;
  const std::string command =
      absl::StrCat("gnuplot '", dir, "/curves.gp' 2>'", dir, "/gnuplot.log'");
  if (block > 0 && std::system(command.c_str()) != 0) {
    return absl::InternalError(absl::StrCat(
        "gnuplot failed to draw curves.png (the CSVs are written); see ", dir,
        "/gnuplot.log"));
  }
  return absl::OkStatus();
}

}  // namespace

std::vector<std::string> LifelongMethodNames() {
  std::vector<std::string> names;
  for (const MethodSpec& s : Specs()) names.push_back(s.name);
  return names;
}

absl::Status RunLifelong(const LifelongOptions& options) {
  std::vector<MethodSpec> specs;
  for (const MethodSpec& s : Specs()) {
    if (options.methods.empty() ||
        std::find(options.methods.begin(), options.methods.end(), s.name) !=
            options.methods.end()) {
      specs.push_back(s);
    }
  }
  for (const std::string& m : options.methods) {
    const auto names = LifelongMethodNames();
    if (std::find(names.begin(), names.end(), m) == names.end()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "unknown method '", m, "'; methods: ", absl::StrJoin(names, ", ")));
    }
  }
  // A memory method needs the server: say so now, not after pre-training.
  if (std::any_of(specs.begin(), specs.end(),
                  [](const MethodSpec& s) { return s.remember; }) &&
      ::access(options.server_binary.c_str(), X_OK) != 0) {
    return absl::NotFoundError(absl::StrCat("no fleetmem-server binary at ",
                                            options.server_binary,
                                            " (--server-binary)"));
  }
  robot::gpl::SetTorchThreads(options.threads);
  Context ctx;
  ctx.options = &options;
  ctx.settings = SettingsFor(options.quick);
  if (options.pretrain_steps > 0)
    ctx.settings.pretrain_steps = options.pretrain_steps;
  if (options.steps_per_segment > 0)
    ctx.settings.steps_per_segment = options.steps_per_segment;
  if (options.negative_candidates > 0) {
    ctx.mining.negative_candidates = options.negative_candidates;
  }
  ctx.server_binary = options.server_binary;
  const auto start = Clock::now();
  absl::StatusOr<Data> data = LoadData(options.data_root, options.max_places);
  if (!data.ok()) return data.status();
  ctx.data = *std::move(data);
  // The output folder only once the input is known to be good.
  std::error_code ec;
  std::filesystem::create_directories(options.out_dir, ec);
  if (ec) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot create ", options.out_dir, ": ", ec.message()));
  }
  // Positives within +-2 files (the tolerance of a correct match), negatives
  // beyond 10 files.
  ctx.mining.positive_radius = 2 * ctx.data.spacing;
  ctx.mining.negative_radius = 10 * ctx.data.spacing;
  Progress(absl::StrFormat(
      "[data] %s: %d places in both seasons, 3 areas, %d queries per season, "
      "%d database "
      "frames; %s settings",
      options.data_root, ctx.data.numbers.size(),
      std::count(ctx.data.query.begin(), ctx.data.query.end(), true),
      ctx.data.numbers.size() -
          std::count(ctx.data.query.begin(), ctx.data.query.end(), true),
      options.quick ? "quick" : "full"));
  if (absl::Status s = WriteConfigs(ctx); !s.ok()) return s;
  if (absl::Status s = Pretrain(ctx); !s.ok()) return s;
  std::vector<MethodResult> results;
  std::vector<FleetRow> fleet;
  for (const MethodSpec& spec : specs) {
    Progress(absl::StrFormat("[%s] start (%.0f s into the run)", spec.name,
                             Seconds(start)));
    absl::StatusOr<MethodResult> r = spec.name == "fleet_shared"
                                         ? RunFleetShared(ctx, spec, &fleet)
                                         : RunSingleRobot(ctx, spec);
    if (!r.ok()) {
      return absl::Status(
          r.status().code(),
          absl::StrCat("method ", spec.name, ": ", r.status().message()));
    }
    Progress(absl::StrFormat("[%s] WR final %.3f, AE %.3f, RA %.3f (%.0f s)",
                             r->name, r->wr_final, r->ae, r->ra, r->seconds));
    results.push_back(*std::move(r));
  }
  if (absl::Status s = WriteOutputs(ctx, results, fleet); !s.ok()) return s;
  std::string table = "\nmethod             WR final   AE      RA\n";
  for (const MethodResult& r : results) {
    table += absl::StrFormat("%-18s %.3f     %.3f   %.3f\n", r.name, r.wr_final,
                             r.ae, r.ra);
  }
  std::printf(
      "%s\nwritten: "
      "%s/{summary.csv,summary.md,curves.csv,curves.png,fleet.csv} (%.0f s)\n",
      table.c_str(), options.out_dir.c_str(), Seconds(start));
  return absl::OkStatus();
}

}  // namespace fleetmem::eval
