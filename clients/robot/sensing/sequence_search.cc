#include "clients/robot/sensing/sequence_search.h"

#include <algorithm>
#include <cmath>
#include <numeric>

#include "clients/robot/sensing/code_search.h"

namespace fleetmem::robot {
namespace {

// Each candidate's contrast against its frame's list (header).
std::vector<float> Contrast(const SequenceFrame& frame) {
  std::vector<float> scores(frame.candidates.size(), 0.0f);
  if (frame.candidates.empty()) return scores;
  auto [lo, hi] = std::minmax_element(
      frame.candidates.begin(), frame.candidates.end(),
      [](const SequenceCandidate& a, const SequenceCandidate& b) {
        return a.distance < b.distance;
      });
  const float span = hi->distance - lo->distance;
  if (!(span > 0.0f)) return scores;
  for (size_t c = 0; c < scores.size(); ++c) {
    scores[c] = (hi->distance - frame.candidates[c].distance) / span;
  }
  return scores;
}

}  // namespace

std::vector<size_t> RankBySequence(std::span<const SequenceFrame> frames,
                                   const SequenceSearchOptions& options) {
  if (frames.empty()) return {};
  std::vector<size_t> order(frames.back().candidates.size());
  std::iota(order.begin(), order.end(), size_t{0});
  const size_t length = std::max<size_t>(options.length, 1);
  if (length == 1 || frames.size() == 1) return order;
  frames = frames.last(std::min(length, frames.size()));

  // along[i]: distance travelled from frames[0] to frames[i].
  std::vector<double> along(frames.size(), 0.0);
  for (size_t i = 1; i < frames.size(); ++i) {
    along[i] = along[i - 1] + std::max(0.0, frames[i].travelled);
  }
  // best[i][c]: the best path's score ending at candidate c of frame i.
  std::vector<std::vector<float>> best(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    best[i] = Contrast(frames[i]);
    for (size_t c = 0; c < best[i].size(); ++c) {
      float before = 0.0f;  // the path may start here
      for (size_t j = 0; j < i; ++j) {
        const double travelled = along[i] - along[j];
        const double allowed = options.tolerance + options.slack * travelled;
        for (size_t a = 0; a < best[j].size(); ++a) {
          if (best[j][a] <= before) continue;
          const double apart = PlaceDistance(frames[j].candidates[a].place,
                                             frames[i].candidates[c].place);
          if (std::abs(apart - travelled) <= allowed) before = best[j][a];
        }
      }
      best[i][c] += before;
    }
  }
  const std::vector<float>& last = best.back();
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return last[a] > last[b]; });
  return order;
}

std::vector<core::Place> SequencePlaces(std::span<const SequenceFrame> frames,
                                        const SequenceSearchOptions& options,
                                        size_t k) {
  std::vector<core::Place> places;
  if (frames.empty()) return places;
  const std::vector<size_t> order = RankBySequence(frames, options);
  for (size_t i = 0; i < std::min(k, order.size()); ++i) {
    places.push_back(frames.back().candidates[order[i]].place);
  }
  return places;
}

void SequenceWindow::Add(const core::Place& place,
                         std::vector<SequenceCandidate> candidates) {
  SequenceFrame frame;
  frame.travelled = frames_.empty() ? 0.0 : PlaceDistance(last_place_, place);
  frame.candidates = std::move(candidates);
  last_place_ = place;
  frames_.push_back(std::move(frame));
  if (frames_.size() > std::max<size_t>(length_, 1)) {
    frames_.erase(frames_.begin());
  }
}

void SequenceWindow::Clear() { frames_.clear(); }

}  // namespace fleetmem::robot
