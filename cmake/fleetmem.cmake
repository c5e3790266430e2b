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

# fleetmem_test(NAME SOURCES ... DEPS ... [LABELS ...] [TIMEOUT seconds])
# A GoogleTest binary registered with CTest (tests sit beside the code).
function(fleetmem_test name)
  if(NOT FLEETMEM_BUILD_TESTS)
    return()
  endif()
  cmake_parse_arguments(ARG "" "TIMEOUT" "SOURCES;DEPS;LABELS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY
                        "${CMAKE_BINARY_DIR}/tests")
  target_include_directories(${name} PRIVATE ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS} GTest::gmock GTest::gtest_main)
  if(FLEETMEM_TSAN_ABSL_ANNOTATIONS)
    # ThreadSanitizer build: tell TSan about Debian's uninstrumented
    # absl::Mutex (tools/tsan/absl_mutex_annotations.cc).
    target_sources(${name} PRIVATE
                   ${PROJECT_SOURCE_DIR}/tools/tsan/absl_mutex_annotations.cc)
    target_link_libraries(${name} PRIVATE ${CMAKE_DL_LIBS})
  endif()
  target_compile_definitions(${name} PRIVATE
    FLEETMEM_DATA_DIR="${FLEETMEM_DATA_DIR}"
    FLEETMEM_BIN_DIR="${CMAKE_BINARY_DIR}/bin"
    FLEETMEM_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
  add_test(NAME ${name} COMMAND ${name})
  if(NOT ARG_TIMEOUT)
    set(ARG_TIMEOUT 300)
  endif()
  set_tests_properties(${name} PROPERTIES TIMEOUT ${ARG_TIMEOUT} LABELS "${ARG_LABELS}")
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
