#include "services/core/seq_set.h"

#include <algorithm>
#include <limits>

namespace fleetmem::core {
namespace {

constexpr uint64_t kMaxSeq = std::numeric_limits<uint64_t>::max();

}  // namespace

SeqSet SeqSet::FromIntervals(const std::vector<Interval>& intervals) {
  std::vector<Interval> sorted;
  sorted.reserve(intervals.size());
  for (const Interval& interval : intervals) {
    if (interval.first <= interval.second) sorted.push_back(interval);
  }
  std::sort(sorted.begin(), sorted.end());
  SeqSet set;
  for (const auto& [first, last] : sorted) {
    if (!set.intervals_.empty()) {
      auto back = std::prev(set.intervals_.end());
      // Overlapping or adjacent: extend the previous interval.
      if (back->second == kMaxSeq || first <= back->second + 1) {
        back->second = std::max(back->second, last);
        continue;
      }
    }
    set.intervals_.emplace(first, last);
  }
  for (const auto& [first, last] : set.intervals_)
    set.size_ += last - first + 1;
  return set;
}

bool SeqSet::Contains(uint64_t seq) const {
  auto it = intervals_.upper_bound(seq);
  if (it == intervals_.begin()) return false;
  --it;
  return seq <= it->second;
}

bool SeqSet::Insert(uint64_t seq) {
  auto next = intervals_.upper_bound(seq);  // first interval starting > seq
  auto prev = next == intervals_.begin() ? intervals_.end() : std::prev(next);
  if (prev != intervals_.end() && seq <= prev->second) return false;

  const bool joins_prev =
      prev != intervals_.end() && seq > 0 && prev->second == seq - 1;
  const bool joins_next =
      next != intervals_.end() && seq < kMaxSeq && next->first == seq + 1;
  if (joins_prev && joins_next) {
    prev->second = next->second;
    intervals_.erase(next);
  } else if (joins_prev) {
    prev->second = seq;
  } else if (joins_next) {
    const uint64_t last = next->second;
    intervals_.erase(next);
    intervals_.emplace(seq, last);
  } else {
    intervals_.emplace(seq, seq);
  }
  ++size_;
  return true;
}

std::vector<SeqSet::Interval> SeqSet::Intervals() const {
  return {intervals_.begin(), intervals_.end()};
}

uint64_t SeqSet::max() const {
  return intervals_.empty() ? 0 : intervals_.rbegin()->second;
}

}  // namespace fleetmem::core
