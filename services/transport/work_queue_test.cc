#include "services/transport/work_queue.h"

#include <algorithm>
#include <atomic>
#include <thread>
#include <vector>

#include "absl/synchronization/notification.h"
#include "gtest/gtest.h"

namespace fleetmem::transport {
namespace {

TEST(WorkQueueTest, RunsEveryAcceptedTask) {
  std::atomic<int> runs{0};
  {
    WorkQueue queue({.threads = 3, .max_queued = 1000});
    EXPECT_EQ(queue.threads(), 3u);
    for (int i = 0; i < 200; ++i) {
      ASSERT_TRUE(queue.TrySubmit([&runs] { runs.fetch_add(1); }));
    }
    queue.Stop();
    EXPECT_EQ(runs.load(), 200);
  }
}

TEST(WorkQueueTest, RefusesWhenQueueIsFull) {
  WorkQueue queue({.threads = 1, .max_queued = 2});
  absl::Notification started, release;
  ASSERT_TRUE(queue.TrySubmit([&] {
    started.Notify();
    release.WaitForNotification();
  }));
  started.WaitForNotification();  // the only worker is busy now
  std::atomic<int> runs{0};
  EXPECT_TRUE(queue.TrySubmit([&runs] { runs.fetch_add(1); }));
  EXPECT_TRUE(queue.TrySubmit([&runs] { runs.fetch_add(1); }));
  EXPECT_FALSE(queue.TrySubmit([&runs] { runs.fetch_add(100); }));
  EXPECT_EQ(queue.queued(), 2u);
  release.Notify();
  queue.Stop();  // drains the two queued tasks
  EXPECT_EQ(runs.load(), 2);
}

TEST(WorkQueueTest, RefusesAfterStop) {
  WorkQueue queue({.threads = 2, .max_queued = 10});
  queue.Stop();
  queue.Stop();  // idempotent
  bool ran = false;
  EXPECT_FALSE(queue.TrySubmit([&ran] { ran = true; }));
  EXPECT_FALSE(ran);
}

TEST(WorkQueueTest, DefaultThreadsIsTwiceTheCores) {
  size_t want = std::max<size_t>(2, 2 * std::thread::hardware_concurrency());
  EXPECT_EQ(WorkerThreads({}), want);
  EXPECT_EQ(WorkerThreads({.threads = 5}), 5u);
}

}  // namespace
}  // namespace fleetmem::transport
