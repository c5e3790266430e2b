# Helpers shared by every module's CMakeLists.txt.

# fleetmem_library(NAME SOURCES ... [PUBLIC_DEPS ...] [PRIVATE_DEPS ...])
# One static library per module. Headers are included as
# "services/<module>/<file>.h" (or "clients/..."), from the project root.
function(fleetmem_library name)
  cmake_parse_arguments(ARG "" "" "SOURCES;PUBLIC_DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(${name} STATIC ${ARG_SOURCES})
  target_include_directories(${name} PUBLIC ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name} PUBLIC ${ARG_PUBLIC_DEPS} PRIVATE ${ARG_PRIVATE_DEPS})
  target_compile_options(${name} PRIVATE -Wall -Wextra -Wno-unused-parameter)
endfunction()

# fleetmem_test(NAME SOURCES ... DEPS ... [LABELS ...] [TIMEOUT seconds]
#               [PROCESSORS n] [RESOURCE_LOCK ...] [ENVIRONMENT ...])
# A GoogleTest binary registered with CTest (tests sit beside the code).
# LABELS name its tier and kind (docs/testing.md): "unit" when none is given.
# TIMEOUT defaults to 300 s; PROCESSORS (default 1) is how many cores it
# keeps busy, so that `ctest -j` never runs more than the machine has.
function(fleetmem_test name)
  if(NOT FLEETMEM_BUILD_TESTS)
    return()
  endif()
  cmake_parse_arguments(ARG "" "TIMEOUT;PROCESSORS"
                        "SOURCES;DEPS;LABELS;RESOURCE_LOCK;ENVIRONMENT" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY
                        "${CMAKE_BINARY_DIR}/tests")
  target_include_directories(${name} PRIVATE ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS} fleetmem_paths GTest::gmock
                        GTest::gtest_main)
  # The tests' own files at FLEETMEM_TEST_OPT (the libraries they test keep
  # the build's -O2, or the sanitizer build's -O1): test code is compiled far
  # more than it runs (docs/testing.md has the compile times).
  target_compile_options(${name} PRIVATE
                         $<$<CONFIG:RelWithDebInfo,Release>:${FLEETMEM_TEST_OPT}>)
  if(FLEETMEM_TSAN_ABSL_ANNOTATIONS)
    # ThreadSanitizer build: tell TSan about Debian's uninstrumented
    # absl::Mutex (tools/tsan/absl_mutex_annotations.cc).
    target_sources(${name} PRIVATE
                   ${PROJECT_SOURCE_DIR}/tools/tsan/absl_mutex_annotations.cc)
    target_link_libraries(${name} PRIVATE ${CMAKE_DL_LIBS})
  endif()
  add_test(NAME ${name} COMMAND ${name})
  fleetmem_test_properties(${name} TIMEOUT ${ARG_TIMEOUT}
    PROCESSORS ${ARG_PROCESSORS} LABELS ${ARG_LABELS}
    RESOURCE_LOCK ${ARG_RESOURCE_LOCK} ENVIRONMENT ${ARG_ENVIRONMENT})
endfunction()

# fleetmem_test_properties(NAME [TIMEOUT s] [PROCESSORS n] [LABELS ...]
#                          [RESOURCE_LOCK ...] [ENVIRONMENT ...] [COST c])
# The properties every test gets, with fleetmem_test's defaults; also for
# tests added with add_test (scripts).
function(fleetmem_test_properties name)
  cmake_parse_arguments(ARG "" "TIMEOUT;PROCESSORS;COST"
                        "LABELS;RESOURCE_LOCK;ENVIRONMENT" ${ARGN})
  if(NOT ARG_TIMEOUT)
    set(ARG_TIMEOUT 300)
  endif()
  if(NOT ARG_PROCESSORS)
    set(ARG_PROCESSORS 1)
  endif()
  if(NOT ARG_LABELS)
    set(ARG_LABELS unit)
  endif()
  set_tests_properties(${name} PROPERTIES TIMEOUT ${ARG_TIMEOUT}
                       PROCESSORS ${ARG_PROCESSORS} LABELS "${ARG_LABELS}")
  if(ARG_RESOURCE_LOCK)
    set_tests_properties(${name} PROPERTIES RESOURCE_LOCK "${ARG_RESOURCE_LOCK}")
  endif()
  if(ARG_ENVIRONMENT)
    set_tests_properties(${name} PROPERTIES ENVIRONMENT "${ARG_ENVIRONMENT}")
  endif()
  if(ARG_COST)
    set_tests_properties(${name} PROPERTIES COST ${ARG_COST})
  endif()
endfunction()

# fleetmem_fuzzer(NAME SOURCES ... DEPS ...)
# A libFuzzer harness (clang, FLEETMEM_BUILD_FUZZ=ON); its seed corpus is
# fuzz_corpus/NAME/ beside the source. `make fuzz` builds and runs them all.
function(fleetmem_fuzzer name)
  if(NOT FLEETMEM_BUILD_FUZZ)
    return()
  endif()
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY
                        "${CMAKE_BINARY_DIR}/fuzz")
  target_include_directories(${name} PRIVATE ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS})
  target_link_options(${name} PRIVATE -fsanitize=fuzzer)
  add_dependencies(fleetmem_fuzzers ${name})
  file(APPEND "${CMAKE_BINARY_DIR}/fuzz/fuzzers.txt"
       "${name} ${CMAKE_CURRENT_SOURCE_DIR}/fuzz_corpus/${name}\n")
endfunction()

# fleetmem_proto_library(NAME PROTO file.proto [DEPS fleetmem_api])
# A static library of the C++ code protoc generates for a private .proto of a
# module (storage records, server config, credentials file, robot state). The
# generated header is included as "<module path>/<file>.pb.h". With DEPS
# fleetmem_api the .proto may import "fleetmem/v1/memory.proto".
function(fleetmem_proto_library name)
  cmake_parse_arguments(ARG "" "PROTO" "DEPS" ${ARGN})
  set(import_args "")
  set(import_deps "")
  if("fleetmem_api" IN_LIST ARG_DEPS)
    set(import_args --proto_path=${PROJECT_SOURCE_DIR}/proto
                    --proto_path=${GOOGLEAPIS_DIR})
    set(import_deps ${PROJECT_SOURCE_DIR}/proto/fleetmem/v1/memory.proto)
  endif()
  set(gen_dir ${CMAKE_CURRENT_BINARY_DIR}/gen)
  file(RELATIVE_PATH rel ${PROJECT_SOURCE_DIR}
       ${CMAKE_CURRENT_SOURCE_DIR}/${ARG_PROTO})
  string(REGEX REPLACE "\\.proto$" "" stem ${rel})
  file(MAKE_DIRECTORY ${gen_dir})
  add_custom_command(
    OUTPUT ${gen_dir}/${stem}.pb.cc ${gen_dir}/${stem}.pb.h
    COMMAND protobuf::protoc
    ARGS --proto_path=${PROJECT_SOURCE_DIR} ${import_args} --cpp_out=${gen_dir}
         ${CMAKE_CURRENT_SOURCE_DIR}/${ARG_PROTO}
    DEPENDS ${ARG_PROTO} ${import_deps}
    COMMENT "Generating ${rel}")
  add_library(${name} STATIC ${gen_dir}/${stem}.pb.cc)
  target_include_directories(${name} PUBLIC ${gen_dir})
  target_link_libraries(${name} PUBLIC protobuf::libprotobuf ${ARG_DEPS})
endfunction()
