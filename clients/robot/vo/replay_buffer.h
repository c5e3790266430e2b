// CL-SLAM's replay buffer (learning.md): one buffer per environment of at
// most `capacity` samples (100 in the public code). A sample enters only if
// the cosine similarity of its feature to every stored one is below
// `max_similarity` (0.95); when a buffer is then over capacity, the most
// redundant sample goes: one of the closest pair of features.
//
// Built on the static memory's own algorithms (services/core): features are
// L2-normalised as codes are (core::NormalizedCode), so the Euclidean
// distance d of two features gives their cosine 1 - d^2 / 2, and the closest
// pair is the one core::ClosestPairTracker keeps for forgetting (Eqs. 16-17)
// without an O(K^2) scan. Of that pair the later sample is dropped: the
// earlier one has been replayed for longer and stays the environment's
// representative.
#ifndef FLEETMEM_CLIENTS_ROBOT_VO_REPLAY_BUFFER_H_
#define FLEETMEM_CLIENTS_ROBOT_VO_REPLAY_BUFFER_H_

#include <cstdint>
#include <map>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "clients/robot/learning/depth_pose_model.h"
#include "services/core/closest_pair.h"

namespace fleetmem::vo {

struct ReplayOptions {
  // Samples per environment (CL-SLAM's public code: 100).
  size_t capacity = 100;
  // A sample is admitted only below this cosine similarity to every stored
  // one (CL-SLAM's public code: 0.95).
  double max_similarity = 0.95;
};

class ReplayBuffer {
 public:
  explicit ReplayBuffer(const ReplayOptions& options = {});

  enum class Outcome { kAdmitted, kAdmittedWithEviction, kTooSimilar };
  // Offers a sample with its feature (all features of a buffer have one
  // dimension; an all-zero feature is refused as too similar).
  Outcome Offer(std::span<const float> feature, Triplet sample);
  // A uniformly drawn sample; the buffer must not be empty.
  const Triplet& Draw(std::mt19937_64& rng) const;

  size_t size() const { return entries_.size(); }
  bool empty() const { return entries_.empty(); }
  // Ids of the stored samples (0, 1, ... in order of admission).
  std::vector<uint64_t> Ids() const;
  uint64_t evicted() const { return evicted_; }
  uint64_t refused() const { return refused_; }

 private:
  struct Entry {
    std::vector<float> feature;  // unit length
    Triplet sample;
  };
  ReplayOptions options_;
  std::map<uint64_t, Entry> entries_;
  core::ClosestPairTracker pairs_;
  uint64_t next_id_ = 0;
  uint64_t evicted_ = 0;
  uint64_t refused_ = 0;
};

// One buffer per environment; the generalizer's batch takes one random
// sample from each environment other than the current one (CL-SLAM Sec. 5).
class ReplayMemory {
 public:
  explicit ReplayMemory(const ReplayOptions& options = {})
      : options_(options) {}
  ReplayBuffer::Outcome Offer(const std::string& environment,
                              std::span<const float> feature, Triplet sample);
  std::vector<Triplet> DrawOthers(const std::string& current,
                                  std::mt19937_64& rng) const;
  const std::map<std::string, ReplayBuffer>& buffers() const {
    return buffers_;
  }

 private:
  ReplayOptions options_;
  std::map<std::string, ReplayBuffer> buffers_;
};

}  // namespace fleetmem::vo

#endif  // FLEETMEM_CLIENTS_ROBOT_VO_REPLAY_BUFFER_H_
