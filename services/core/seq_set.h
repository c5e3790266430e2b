// The set of sequence numbers a fleet has received from one robot, as sorted
// disjoint intervals: exact duplicate detection by (robot, seq) that stays
// one interval per robot while uploads arrive in order.
#ifndef FLEETMEM_SERVICES_CORE_SEQ_SET_H_
#define FLEETMEM_SERVICES_CORE_SEQ_SET_H_

#include <cstdint>
#include <map>
#include <utility>
#include <vector>

namespace fleetmem::core {

class SeqSet {
 public:
  // Closed intervals [first, last].
  using Interval = std::pair<uint64_t, uint64_t>;

  SeqSet() = default;
  // Restores a set from Intervals() output (overlaps are merged).
  static SeqSet FromIntervals(const std::vector<Interval>& intervals);

  bool Contains(uint64_t seq) const;
  // Adds seq; false if it was already present.
  bool Insert(uint64_t seq);
  std::vector<Interval> Intervals() const;
  // Number of sequence numbers held.
  uint64_t size() const { return size_; }
  // Largest sequence number held (0 when empty).
  uint64_t max() const;

 private:
  std::map<uint64_t, uint64_t> intervals_;  // first -> last
  uint64_t size_ = 0;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_SEQ_SET_H_
