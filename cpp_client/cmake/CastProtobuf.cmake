# Code generation from .proto files at build time (generated code is never
# committed: it goes into the build directory).
#
#   cast_add_entry_types(<target> FILES a.proto [b.proto ...]
#                        [IMPORT_DIRS dir ...] [GRPC])
#
# makes a static library <target> holding the C++ classes of the messages in
# the given files; link it next to cast::client. IMPORT_DIRS are the protoc
# import paths (default: the calling directory). The name protoc gives a file
# is its path relative to the import dir that contains it, and that name is
# what the schema registry keys types by: compile a shared .proto with the
# same import dir in every language, or the server sees two different files.
# GRPC also generates service stubs (the library uses it for cast/v1).

include_guard(GLOBAL)

function(cast_add_entry_types target)
  cmake_parse_arguments(ARG "GRPC" "" "FILES;IMPORT_DIRS" ${ARGN})
  if(NOT ARG_FILES)
    message(FATAL_ERROR "cast_add_entry_types(${target}): give the .proto files with FILES")
  endif()
  # Imported targets are visible only in the directory that found them: a
  # project that brought in cpp_client with add_subdirectory() has none yet.
  if(NOT TARGET protobuf::protoc OR NOT TARGET protobuf::libprotobuf)
    find_package(Protobuf REQUIRED)
  endif()
  if(ARG_GRPC AND NOT TARGET gRPC::grpc_cpp_plugin)
    find_package(gRPC CONFIG REQUIRED)
  endif()
  if(NOT ARG_IMPORT_DIRS)
    set(ARG_IMPORT_DIRS "${CMAKE_CURRENT_SOURCE_DIR}")
  endif()
  set(import_dirs "")
  set(import_args "")
  foreach(dir IN LISTS ARG_IMPORT_DIRS)
    get_filename_component(dir "${dir}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
    list(APPEND import_dirs "${dir}")
    list(APPEND import_args "-I${dir}")
  endforeach()

  set(gen_dir "${CMAKE_CURRENT_BINARY_DIR}/${target}_generated")
  file(MAKE_DIRECTORY "${gen_dir}")
  set(sources "")
  set(headers "")
  foreach(proto IN LISTS ARG_FILES)
    get_filename_component(abs "${proto}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
    # The file's protoc name: its path below the first import dir holding it.
    set(rel "")
    foreach(dir IN LISTS import_dirs)
      file(RELATIVE_PATH candidate "${dir}" "${abs}")
      if(NOT candidate MATCHES "^\\.\\./")
        set(rel "${candidate}")
        break()
      endif()
    endforeach()
    if(rel STREQUAL "")
      message(FATAL_ERROR "cast_add_entry_types(${target}): ${abs} is not below any IMPORT_DIRS (${import_dirs})")
    endif()
    string(REGEX REPLACE "\\.proto$" "" stem "${rel}")
    set(outputs "${gen_dir}/${stem}.pb.cc" "${gen_dir}/${stem}.pb.h")
    set(plugin_args "")
    set(plugin_deps "")
    if(ARG_GRPC)
      list(APPEND outputs "${gen_dir}/${stem}.grpc.pb.cc" "${gen_dir}/${stem}.grpc.pb.h")
      set(plugin_args "--grpc_out=${gen_dir}" "--plugin=protoc-gen-grpc=$<TARGET_FILE:gRPC::grpc_cpp_plugin>")
      set(plugin_deps gRPC::grpc_cpp_plugin)
    endif()
    add_custom_command(
      OUTPUT ${outputs}
      COMMAND protobuf::protoc "--cpp_out=${gen_dir}" ${plugin_args} ${import_args} "${abs}"
      DEPENDS "${abs}" protobuf::protoc ${plugin_deps}
      COMMENT "protoc ${rel} (${target})"
      VERBATIM)
    foreach(out IN LISTS outputs)
      if(out MATCHES "\\.cc$")
        list(APPEND sources "${out}")
      else()
        list(APPEND headers "${out}")
      endif()
    endforeach()
  endforeach()

  add_library(${target} STATIC ${sources} ${headers})
  target_include_directories(${target} PUBLIC "$<BUILD_INTERFACE:${gen_dir}>")
  target_link_libraries(${target} PUBLIC protobuf::libprotobuf)
  if(ARG_GRPC)
    target_link_libraries(${target} PUBLIC gRPC::grpc++)
  endif()
  # Generated code is not ours to warn about, and must link into shared
  # objects too. protoc gives every .pb.cc file-local arrays of the same
  # names, so the files cannot share a unity (jumbo) translation unit: a
  # project built with CMAKE_UNITY_BUILD compiles them one by one.
  set_target_properties(${target} PROPERTIES POSITION_INDEPENDENT_CODE ON UNITY_BUILD OFF)
endfunction()
