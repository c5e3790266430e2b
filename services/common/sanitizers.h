// Whether this build runs under a sanitizer whose allocator replaces the C
// library's (AddressSanitizer, ThreadSanitizer): tests of memory use and of
// the C library's heap skip their bounds there. GCC defines
// __SANITIZE_ADDRESS__ / __SANITIZE_THREAD__; clang answers __has_feature.
#ifndef FLEETMEM_SERVICES_COMMON_SANITIZERS_H_
#define FLEETMEM_SERVICES_COMMON_SANITIZERS_H_

namespace fleetmem::common {

#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
inline constexpr bool kSanitizerAllocator = true;
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer)
inline constexpr bool kSanitizerAllocator = true;
#else
inline constexpr bool kSanitizerAllocator = false;
#endif
#else
inline constexpr bool kSanitizerAllocator = false;
#endif

}  // namespace fleetmem::common

#endif  // FLEETMEM_SERVICES_COMMON_SANITIZERS_H_
