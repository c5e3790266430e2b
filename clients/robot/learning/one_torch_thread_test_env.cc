// Linked into every libtorch test binary (learning, VO): torch computes on
// one intra-op thread whatever the machine, so that a test's time and
// results do not depend on the cores or on what else runs. CTest gives each
// of these tests one processor and OMP_NUM_THREADS=1 (docs/testing.md).
#include "clients/robot/learning/gpl_model.h"
#include "gtest/gtest.h"

namespace {

class OneTorchThread : public ::testing::Environment {
 public:
  void SetUp() override { fleetmem::robot::gpl::SetTorchThreads(1); }
};

::testing::Environment* const kOneTorchThread =
    ::testing::AddGlobalTestEnvironment(new OneTorchThread);

}  // namespace
