// Time as the server's components read it where time decides behaviour (a
// lease that expires, a fencing window): the real clock in production, a
// clock a test moves by hand (testing/manual_clock.h) in tests.
#ifndef FLEETMEM_SERVICES_COMMON_CLOCK_H_
#define FLEETMEM_SERVICES_COMMON_CLOCK_H_

#include "absl/time/clock.h"
#include "absl/time/time.h"

namespace fleetmem {

// Thread-safe.
class Clock {
 public:
  virtual ~Clock() = default;
  virtual absl::Time Now() const = 0;

  // The process's clock (absl::Now); lives as long as the process.
  static const Clock& Real();
};

inline const Clock& Clock::Real() {
  class RealClock final : public Clock {
   public:
    absl::Time Now() const override { return absl::Now(); }
  };
  static const RealClock* const kReal = new RealClock();
  return *kReal;
}

}  // namespace fleetmem

#endif  // FLEETMEM_SERVICES_COMMON_CLOCK_H_
