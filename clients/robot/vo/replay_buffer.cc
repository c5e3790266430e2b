#include "clients/robot/vo/replay_buffer.h"

#include <iterator>

#include "Eigen/Core"
#include "services/core/feature_space.h"

namespace fleetmem::vo {

ReplayBuffer::ReplayBuffer(const ReplayOptions& options) : options_(options) {}

ReplayBuffer::Outcome ReplayBuffer::Offer(std::span<const float> feature,
                                          Triplet sample) {
  std::vector<float> unit = core::NormalizedCode(feature);
  bool zero = true;
  for (float v : unit) zero = zero && v == 0.0f;
  if (zero) {
    ++refused_;
    return Outcome::kTooSimilar;
  }
  for (const auto& [id, entry] : entries_) {
    // Unit vectors: cos = 1 - d^2 / 2 with d = core::CodeDistance.
    const double d = core::CodeDistance(unit, entry.feature);
    if (1.0 - d * d / 2.0 >= options_.max_similarity) {
      ++refused_;
      return Outcome::kTooSimilar;
    }
  }
  const uint64_t id = next_id_++;
  pairs_.Insert(id, Eigen::Map<const Eigen::VectorXf>(
                        unit.data(), static_cast<Eigen::Index>(unit.size())));
  entries_.emplace(id, Entry{std::move(unit), std::move(sample)});
  if (entries_.size() <= options_.capacity) return Outcome::kAdmitted;
  const uint64_t drop = pairs_.Closest()->b;  // the later of the pair
  pairs_.Remove(drop);
  entries_.erase(drop);
  ++evicted_;
  return Outcome::kAdmittedWithEviction;
}

const Triplet& ReplayBuffer::Draw(std::mt19937_64& rng) const {
  std::uniform_int_distribution<size_t> pick(0, entries_.size() - 1);
  return std::next(entries_.begin(), static_cast<long>(pick(rng)))
      ->second.sample;
}

std::vector<uint64_t> ReplayBuffer::Ids() const {
  std::vector<uint64_t> ids;
  for (const auto& [id, entry] : entries_) ids.push_back(id);
  return ids;
}

ReplayBuffer::Outcome ReplayMemory::Offer(const std::string& environment,
                                          std::span<const float> feature,
                                          Triplet sample) {
  auto it = buffers_.try_emplace(environment, options_).first;
  return it->second.Offer(feature, std::move(sample));
}

std::vector<Triplet> ReplayMemory::DrawOthers(const std::string& current,
                                              std::mt19937_64& rng) const {
  std::vector<Triplet> drawn;
  for (const auto& [environment, buffer] : buffers_) {
    if (environment != current && !buffer.empty()) {
      drawn.push_back(buffer.Draw(rng));
    }
  }
  return drawn;
}

}  // namespace fleetmem::vo
