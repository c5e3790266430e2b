// A Clock (services/common/clock.h) that moves only when a test says so.
#ifndef FLEETMEM_SERVICES_COMMON_TESTING_MANUAL_CLOCK_H_
#define FLEETMEM_SERVICES_COMMON_TESTING_MANUAL_CLOCK_H_

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "services/common/clock.h"

namespace fleetmem::testing {

class ManualClock final : public Clock {
 public:
  explicit ManualClock(absl::Time start = absl::FromUnixSeconds(1'800'000'000))
      : now_(start) {}

  absl::Time Now() const override {
    absl::MutexLock lock(&mu_);
    return now_;
  }

  void Advance(absl::Duration by) {
    absl::MutexLock lock(&mu_);
    now_ += by;
  }

 private:
  mutable absl::Mutex mu_;
  absl::Time now_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fleetmem::testing

#endif  // FLEETMEM_SERVICES_COMMON_TESTING_MANUAL_CLOCK_H_
