// Relocalisation over a sequence of frames when the map is a fleet memory:
// the robot sees, for each of its last N frames, only the k nearest traces
// the server returned (place and code distance), not a similarity matrix
// over an ordered map as SeqSLAM does (tools/eval's SequenceSimilarity).
// The map has gaps (places forgotten or never driven) and traces of several
// robots, each in the fleet's map frame.
//
// The search is a best-path alignment (Viterbi) over the candidate lists:
// a path picks at most one candidate per frame, in order; a step from
// candidate a (frame i) to candidate b (frame j > i) is allowed when the
// distance between their places agrees with the distance the robot
// travelled from frame i to frame j (its odometry), within
//   tolerance + slack * travelled
// (turns make the straight line shorter than the path; odometry drifts).
// Frames a path skips (no consistent candidate: a gap in the memory, or the
// place not in that frame's top k) add nothing. A candidate's score in its
// frame is its contrast against the frame's list,
//   s = (d_k - d) / (d_k - d_1),
// 1 for the nearest, 0 for the k-th (and for a frame whose k distances are
// equal), so that frames of different contrast weigh alike, as SeqSLAM's
// local normalisation does. The current frame's candidates are re-ranked by
// the best path ending at each of them (ties keep the server's order).
//
// Compared with SeqSLAM: no velocity search (the robot's odometry gives the
// step); no map order needed (places, not indices); a hypothesis must be
// among the current frame's k candidates (a place the server did not
// return for the current frame is never proposed: ask for more k than you
// report).
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_SEQUENCE_SEARCH_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_SEQUENCE_SEARCH_H_

#include <cstddef>
#include <span>
#include <vector>

#include "services/core/types.h"

namespace fleetmem::robot {

// One trace the map returned for a frame.
struct SequenceCandidate {
  core::Place place;
  float distance = 0.0f;  // code distance, smaller is nearer
};

// One frame of the robot's sequence.
struct SequenceFrame {
  // Distance the robot travelled since the previous frame (place units;
  // ignored for the first frame of a sequence).
  double travelled = 0.0;
  // The map's answer for this frame, nearest first (may be empty).
  std::vector<SequenceCandidate> candidates;
};

struct SequenceSearchOptions {
  // Frames matched together, the current one included; 1 = single frame
  // (the server's order is kept). Default chosen by measurement
  // (docs/robot.md, "Relocalising over a sequence").
  size_t length = 10;
  // Allowed disagreement between a step's place distance and the distance
  // travelled (place units; the robot's match radius is a good value).
  double tolerance = 20.0;
  // Further allowance per unit travelled (turns, odometry drift).
  double slack = 0.25;
};

// The current frame's (frames.back()) candidates re-ranked by their best
// path over `frames` (oldest first): indices into
// frames.back().candidates, best first. Only the last options.length frames
// are used.
std::vector<size_t> RankBySequence(std::span<const SequenceFrame> frames,
                                   const SequenceSearchOptions& options);

// The places of the first min(k, size) of the current frame's candidates
// in RankBySequence's order: what a relocalisation over the sequence
// answers, for FirstCorrectRank.
std::vector<core::Place> SequencePlaces(std::span<const SequenceFrame> frames,
                                        const SequenceSearchOptions& options,
                                        size_t k);

// The last `length` frames of a robot, for RankBySequence. A frame with no
// answer (the server unreachable or the memory empty) is kept as an empty
// frame so that the travelled distances still add up.
class SequenceWindow {
 public:
  explicit SequenceWindow(size_t length) : length_(length) {}
  // Adds a frame made at `place` (the robot's own estimate: odometry; the
  // travelled distance is taken from the previous frame's place).
  void Add(const core::Place& place, std::vector<SequenceCandidate> candidates);
  // Forgets the sequence (the robot was moved, or a new drive starts).
  void Clear();
  std::span<const SequenceFrame> frames() const { return frames_; }

 private:
  size_t length_;
  std::vector<SequenceFrame> frames_;  // oldest first, at most length_
  core::Place last_place_;
};

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_SEQUENCE_SEARCH_H_
