# fleetmem_bytes_literal(FILE BYTES_VAR SIZE_VAR): the bytes of FILE as a C
# initializer list ("0x12,0x34,...") and their count, for the scripts that
# embed files in C++ sources (embed_files.cmake, embed_bytes.cmake).
function(fleetmem_bytes_literal file bytes_var size_var)
  file(READ ${file} hex HEX)
  string(LENGTH "${hex}" hex_length)
  math(EXPR size "${hex_length} / 2")
  string(REGEX REPLACE "([0-9a-f][0-9a-f])" "0x\\1," bytes "${hex}")
  set(${bytes_var} "${bytes}" PARENT_SCOPE)
  set(${size_var} ${size} PARENT_SCOPE)
endfunction()
