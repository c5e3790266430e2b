// ThreadSanitizer annotations for Debian's prebuilt absl::Mutex.
//
// libabsl_synchronization.so is not built with -fsanitize=thread, so its
// Mutex carries no TSan annotations and TSan cannot see that a MutexLock
// orders two accesses: every absl::Mutex-protected access would be reported
// as a race. Linked into the TSan build's test binaries only (`make
// test-tsan`), this file defines Mutex::Lock/Unlock/ReaderLock/ReaderUnlock/
// TryLock/ReaderTryLock and CondVar::Wait/WaitWithDeadline/WaitWithTimeout
// in the executable: they tell TSan about the lock (sanitizer/
// tsan_interface.h) around the real functions, found with dlsym(RTLD_NEXT).
// Await/LockWhen are not annotated: code that waits on a Condition (the
// transport's work queue and shutdown) is not run under TSan
// (docs/reliability.md).
#include <dlfcn.h>
#include <sanitizer/tsan_interface.h>

#include <cstdio>
#include <cstdlib>

#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"

namespace {

template <typename Function>
Function Real(const char* symbol) {
  void* found = dlsym(RTLD_NEXT, symbol);
  if (found == nullptr) {
    std::fprintf(stderr, "absl_mutex_annotations: no %s in the process\n",
                 symbol);
    std::abort();
  }
  return reinterpret_cast<Function>(found);
}

using Method = void (*)(absl::Mutex*);
using TryMethod = bool (*)(absl::Mutex*);

}  // namespace

namespace absl {
ABSL_NAMESPACE_BEGIN

void Mutex::Lock() {
  static const Method real = Real<Method>("_ZN4absl7debian35Mutex4LockEv");
  __tsan_mutex_pre_lock(this, 0);
  real(this);
  __tsan_mutex_post_lock(this, 0, 0);
}

void Mutex::Unlock() {
  static const Method real = Real<Method>("_ZN4absl7debian35Mutex6UnlockEv");
  __tsan_mutex_pre_unlock(this, 0);
  real(this);
  __tsan_mutex_post_unlock(this, 0);
}

void Mutex::ReaderLock() {
  static const Method real =
      Real<Method>("_ZN4absl7debian35Mutex10ReaderLockEv");
  __tsan_mutex_pre_lock(this, __tsan_mutex_read_lock);
  real(this);
  __tsan_mutex_post_lock(this, __tsan_mutex_read_lock, 0);
}

void Mutex::ReaderUnlock() {
  static const Method real =
      Real<Method>("_ZN4absl7debian35Mutex12ReaderUnlockEv");
  __tsan_mutex_pre_unlock(this, __tsan_mutex_read_lock);
  real(this);
  __tsan_mutex_post_unlock(this, __tsan_mutex_read_lock);
}

bool Mutex::TryLock() {
  static const TryMethod real =
      Real<TryMethod>("_ZN4absl7debian35Mutex7TryLockEv");
  __tsan_mutex_pre_lock(this, __tsan_mutex_try_lock);
  const bool locked = real(this);
  __tsan_mutex_post_lock(
      this, __tsan_mutex_try_lock | (locked ? 0 : __tsan_mutex_try_lock_failed),
      0);
  return locked;
}

bool Mutex::ReaderTryLock() {
  static const TryMethod real =
      Real<TryMethod>("_ZN4absl7debian35Mutex13ReaderTryLockEv");
  const unsigned flags = __tsan_mutex_read_lock | __tsan_mutex_try_lock;
  __tsan_mutex_pre_lock(this, flags);
  const bool locked = real(this);
  __tsan_mutex_post_lock(
      this, flags | (locked ? 0 : __tsan_mutex_try_lock_failed), 0);
  return locked;
}

// A CondVar wait releases the (exclusively held) mutex inside the library
// and holds it again before it returns: TSan is told of both, or it would
// take the waiter for the mutex's holder throughout (a "double lock" when
// the signaller locks it).
namespace {

void WaitReleases(Mutex* mu) {
  __tsan_mutex_pre_unlock(mu, 0);
  __tsan_mutex_post_unlock(mu, 0);
}

void WaitReacquires(Mutex* mu) {
  __tsan_mutex_pre_lock(mu, 0);
  __tsan_mutex_post_lock(mu, 0, 0);
}

}  // namespace

void CondVar::Wait(Mutex* mu) {
  static const auto real = Real<void (*)(CondVar*, Mutex*)>(
      "_ZN4absl7debian37CondVar4WaitEPNS0_5MutexE");
  WaitReleases(mu);
  real(this, mu);
  WaitReacquires(mu);
}

bool CondVar::WaitWithDeadline(Mutex* mu, absl::Time deadline) {
  static const auto real = Real<bool (*)(CondVar*, Mutex*, absl::Time)>(
      "_ZN4absl7debian37CondVar16WaitWithDeadlineEPNS0_5MutexENS0_4TimeE");
  WaitReleases(mu);
  const bool timed_out = real(this, mu, deadline);
  WaitReacquires(mu);
  return timed_out;
}

// Debian's absl (20220623) implements WaitWithTimeout as WaitWithDeadline
// through the PLT, which lands in the wrapper above: wrapping it too told
// TSan of each release twice ("unlock of an unlocked mutex"). It is
// written here as absl writes it.
bool CondVar::WaitWithTimeout(Mutex* mu, absl::Duration timeout) {
  return WaitWithDeadline(mu, absl::Now() + timeout);
}

ABSL_NAMESPACE_END
}  // namespace absl
