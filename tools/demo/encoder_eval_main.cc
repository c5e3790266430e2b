// fleetmem-encoder-eval: compares the demo's candidate image codes on the
// real Nordland data without a server. For every encoder: summer -> winter
// place recognition by exact nearest-neighbour search (recall@1/@5, WR) over
// the whole route and over the demo's robot stretches, the internal reward
// statistics and the encoding time.
//
//   fleetmem-encoder-eval [--data DIR] [--robots N] [--stretch-length N]
//                         [--encoders a,b,...]
#include <chrono>
#include <cstdio>
#include <iostream>
#include <random>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "clients/robot/sensing/code_search.h"
#include "clients/robot/sensing/image_encoder.h"
#include "clients/robot/sensing/nordland.h"
#include "clients/robot/sensing/rewards.h"
#include "fleetmem_paths.h"
#include "fleetmem_version.h"
#include "services/common/cli_program.h"
#include "services/core/place_metrics.h"

namespace fleetmem::demo {
namespace {

// The command line (CLI11; --name-with-dashes or --name_with_underscores).
struct EncoderEvalFlags {
  std::string data = FLEETMEM_DATA_DIR;
  int robots = 3;
  int stretch_length = 300;
  std::string encoders;
};

EncoderEvalFlags& Flags() {
  static EncoderEvalFlags* flags = new EncoderEvalFlags;
  return *flags;
}

}  // namespace
}  // namespace fleetmem::demo

namespace fleetmem::demo {
namespace {

using robot::BruteForceIndex;
using robot::ExternalRewards;
using robot::FirstCorrectRank;
using robot::ImageEncoder;
using robot::ImageEncoderNames;
using robot::InternalReward;
using robot::kNordlandUnitsPerFile;
using robot::ListNordlandFrames;
using robot::LoadNordlandGrey;
using robot::NewImageEncoderByName;
using robot::RandomShiftCrop;
using robot::ShiftCropOptions;
using robot::SpreadStretches;
using robot::Stretch;
using robot::TripletOptions;

// A query is correct within +-2 files (README.md).
constexpr double kToleranceUnits = 2.0 * kNordlandUnitsPerFile;
constexpr size_t kTopK = 6;

struct Season {
  std::vector<int> numbers;
  std::vector<cv::Mat> images;
};

absl::StatusOr<Season> LoadSeason(const std::string& dir) {
  Season season;
  absl::StatusOr<std::vector<int>> numbers = ListNordlandFrames(dir);
  if (!numbers.ok()) return numbers.status();
  season.numbers = *std::move(numbers);
  for (int number : season.numbers) {
    absl::StatusOr<cv::Mat> image = LoadNordlandGrey(dir, number);
    if (!image.ok()) return image.status();
    season.images.push_back(*std::move(image));
  }
  return season;
}

// Recall over queries `query_rows` of winter against references `db_rows`
// of summer (rows of the same frame list; same row = same place).
core::FirstCorrectRanks Ranks(const std::vector<std::vector<float>>& summer,
                              const std::vector<std::vector<float>>& winter,
                              const Season& season,
                              const std::vector<size_t>& rows) {
  BruteForceIndex index(summer.front().size());
  for (size_t row : rows) index.Add(summer[row], season.numbers[row]);
  core::FirstCorrectRanks ranks;
  for (size_t row : rows) {
    std::vector<core::Place> found;
    for (double x : index.Search(winter[row], kTopK)) found.push_back({.x = x});
    ranks.push_back(
        FirstCorrectRank(found, {.x = static_cast<double>(season.numbers[row])},
                         kToleranceUnits));
  }
  return ranks;
}

// Every frame of both seasons encoded, in row order.
absl::Status EncodeBoth(ImageEncoder& encoder, const Season& summer,
                        const Season& winter,
                        std::vector<std::vector<float>>* summer_codes,
                        std::vector<std::vector<float>>* winter_codes) {
  for (size_t i = 0; i < summer.images.size(); ++i) {
    absl::StatusOr<std::vector<float>> s =
        encoder.EncodeImage(summer.images[i]);
    absl::StatusOr<std::vector<float>> w =
        encoder.EncodeImage(winter.images[i]);
    if (!s.ok()) return s.status();
    if (!w.ok()) return w.status();
    summer_codes->push_back(*std::move(s));
    winter_codes->push_back(*std::move(w));
  }
  return absl::OkStatus();
}

// The rewards over the robot stretches, as the demo computes them: sums of
// R_in and R_ex, and how many R_ex were positive.
struct Rewards {
  double internal_sum = 0.0, external_sum = 0.0;
  size_t external_positive = 0;
};
absl::StatusOr<Rewards> StretchRewards(
    ImageEncoder& encoder, const Season& summer,
    const std::vector<std::vector<float>>& summer_codes,
    const std::vector<Stretch>& stretches) {
  std::mt19937_64 rng(7);
  Rewards rewards;
  for (const Stretch& s : stretches) {
    std::vector<std::vector<float>> codes;
    std::vector<core::Place> x;
    for (size_t i = s.begin; i < s.end; ++i) {
      absl::StatusOr<cv::Mat> moved =
          RandomShiftCrop(summer.images[i], ShiftCropOptions{}, rng);
      if (!moved.ok()) return moved.status();
      absl::StatusOr<std::vector<float>> code = encoder.EncodeImage(*moved);
      if (!code.ok()) return code.status();
      rewards.internal_sum += InternalReward(summer_codes[i], *code);
      codes.push_back(summer_codes[i]);
      x.push_back({.x = static_cast<double>(summer.numbers[i])});
    }
    for (float r : ExternalRewards(codes, x, TripletOptions{})) {
      rewards.external_sum += r;
      rewards.external_positive += r > 0.0f ? 1 : 0;
    }
  }
  return rewards;
}

absl::Status Run() {
  const std::string root = Flags().data + "/nordland";
  absl::StatusOr<Season> summer = LoadSeason(root + "/summer");
  if (!summer.ok()) return summer.status();
  absl::StatusOr<Season> winter = LoadSeason(root + "/winter");
  if (!winter.ok()) return winter.status();
  if (summer->numbers != winter->numbers) {
    return absl::FailedPreconditionError(
        "summer and winter hold different frame numbers");
  }
  absl::StatusOr<std::vector<Stretch>> stretches = SpreadStretches(
      summer->numbers.size(), Flags().robots, Flags().stretch_length);
  if (!stretches.ok()) return stretches.status();
  std::vector<size_t> all_rows, stretch_rows;
  for (size_t i = 0; i < summer->numbers.size(); ++i) all_rows.push_back(i);
  for (const Stretch& s : *stretches) {
    for (size_t i = s.begin; i < s.end; ++i) stretch_rows.push_back(i);
  }

  std::vector<std::string> names = ImageEncoderNames();
  if (!Flags().encoders.empty()) {
    names = absl::StrSplit(Flags().encoders, ',');
  }
  std::printf(
      "Nordland summer -> winter, exact search, correct within +-2 "
      "files; %zu frames, stretches: %zu frames\n",
      all_rows.size(), stretch_rows.size());
  std::printf("%-22s %5s | %6s %6s %6s | %6s %6s %6s | %6s %6s %6s | %6s\n",
              "encoder", "dim", "r@1", "r@5", "WR", "s r@1", "s r@5", "s WR",
              "R_in", "R_ex", "R_ex>0", "us/img");
  for (const std::string& name : names) {
    absl::StatusOr<std::unique_ptr<ImageEncoder>> encoder =
        NewImageEncoderByName(name);
    if (!encoder.ok()) return encoder.status();
    std::vector<std::vector<float>> summer_codes, winter_codes;
    const auto start = std::chrono::steady_clock::now();
    if (absl::Status encoded = EncodeBoth(**encoder, *summer, *winter,
                                          &summer_codes, &winter_codes);
        !encoded.ok()) {
      return encoded;
    }
    const double us_per_image = std::chrono::duration<double, std::micro>(
                                    std::chrono::steady_clock::now() - start)
                                    .count() /
                                (2.0 * all_rows.size());
    absl::StatusOr<Rewards> rewards =
        StretchRewards(**encoder, *summer, summer_codes, *stretches);
    if (!rewards.ok()) return rewards.status();
    const double internal_sum = rewards->internal_sum;
    const double external_sum = rewards->external_sum;
    const size_t external_positive = rewards->external_positive;
    const core::FirstCorrectRanks all =
        Ranks(summer_codes, winter_codes, *summer, all_rows);
    const core::FirstCorrectRanks part =
        Ranks(summer_codes, winter_codes, *summer, stretch_rows);
    std::printf(
        "%-22s %5zu | %6.3f %6.3f %6.3f | %6.3f %6.3f %6.3f | %6.3f %6.3f "
        "%6.3f | %6.1f\n",
        name.c_str(), (*encoder)->dimension(), core::RecallAtK(all, 1),
        core::RecallAtK(all, 5), core::WeightedRecall(all),
        core::RecallAtK(part, 1), core::RecallAtK(part, 5),
        core::WeightedRecall(part), internal_sum / stretch_rows.size(),
        external_sum / stretch_rows.size(),
        static_cast<double>(external_positive) / stretch_rows.size(),
        us_per_image);
    std::fflush(stdout);
  }
  std::printf(
      "r@k/WR: whole route; s r@k/s WR: robot stretches only; R_in, "
      "R_ex: mean rewards over the stretches; R_ex>0: share of "
      "stretch frames with a non-zero triplet loss.\n"
      "Data: Nordland railway footage, NRK (CC BY).\n");
  return absl::OkStatus();
}

}  // namespace
}  // namespace fleetmem::demo

int main(int argc, char** argv) {
  CLI::App app{
      "fleetmem-encoder-eval: compares the demo's image encoders on Nordland "
      "summer -> winter."};
  fleetmem::common::SetUpProgram(app, "fleetmem-encoder-eval");
  fleetmem::demo::EncoderEvalFlags& flags = fleetmem::demo::Flags();
  app.add_option(
      "--data", flags.data,
      "shared data folder (holds nordland/summer and nordland/winter; "
      "default: the checkout's ../shared/data)");
  app.add_option("--robots", flags.robots, "robot stretches of the demo")
      ->capture_default_str();
  app.add_option("--stretch-length,--stretch_length", flags.stretch_length,
                 "frames per robot stretch")
      ->capture_default_str();
  app.add_option("--encoders", flags.encoders,
                 "comma-separated encoder names (default: all)")
      ->capture_default_str();
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  const absl::Status status = fleetmem::demo::Run();
  if (!status.ok()) {
    std::cerr << "fleetmem-encoder-eval: " << status << "\n";
    return 1;
  }
  return 0;
}
