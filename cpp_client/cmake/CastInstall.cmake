# `cmake --install` of the C++ client library (included by cpp_client/CMakeLists.txt when
# CAST_INSTALL is on, the default for a top-level build): what an outside project needs to
# find_package(cast 0.1 CONFIG REQUIRED) and link cast::client, or to use pkg-config.
#
#   PREFIX/include/cast/*.h            the library's headers (the API; docs/cpp.md, "Headers")
#   PREFIX/include/cast/detail/*.h     what their templates need that is not the API (cpp_client/src,
#                                      the rest of the machinery, is not installed)
#   PREFIX/include/cast/v1/*.pb.h      the generated headers of the wire API (raw stubs)
#   PREFIX/lib/libcast_client.a|.so    the library (BUILD_SHARED_LIBS chooses)
#   PREFIX/lib/libcast_v1_proto.a      the wire API's code (linked into a shared library; a
#                                      static one needs it beside it)
#   PREFIX/lib/libcast_testing.a|.so   the testing kit (cast/testing.h, the component `testing`)
#   PREFIX/lib/cmake/cast/             castConfig.cmake, castConfigVersion.cmake, castTargets*.cmake,
#                                      CastProtobuf.cmake (cast_add_entry_types)
#   PREFIX/lib/pkgconfig/cast.pc
include(CMakePackageConfigHelpers)

set(CAST_CMAKE_DIR "${CMAKE_INSTALL_LIBDIR}/cmake/cast")

install(TARGETS cast_client cast_testing cast_v1_proto EXPORT castTargets
  ARCHIVE DESTINATION "${CMAKE_INSTALL_LIBDIR}"
  LIBRARY DESTINATION "${CMAKE_INSTALL_LIBDIR}"
  RUNTIME DESTINATION "${CMAKE_INSTALL_BINDIR}")
install(DIRECTORY "${CMAKE_CURRENT_SOURCE_DIR}/include/cast" DESTINATION "${CMAKE_INSTALL_INCLUDEDIR}")
install(DIRECTORY "${CMAKE_CURRENT_BINARY_DIR}/cast_v1_proto_generated/cast/v1"
  DESTINATION "${CMAKE_INSTALL_INCLUDEDIR}/cast" FILES_MATCHING PATTERN "*.h")
install(EXPORT castTargets NAMESPACE cast:: FILE castTargets.cmake DESTINATION "${CAST_CMAKE_DIR}")

configure_package_config_file("${CMAKE_CURRENT_SOURCE_DIR}/cmake/castConfig.cmake.in"
  "${CMAKE_CURRENT_BINARY_DIR}/castConfig.cmake" INSTALL_DESTINATION "${CAST_CMAKE_DIR}")
# 0.x: a minor release may break the API, so find_package(cast 0.1) takes 0.1.y only.
write_basic_package_version_file("${CMAKE_CURRENT_BINARY_DIR}/castConfigVersion.cmake"
  VERSION "${PROJECT_VERSION}" COMPATIBILITY SameMinorVersion)
install(FILES "${CMAKE_CURRENT_BINARY_DIR}/castConfig.cmake" "${CMAKE_CURRENT_BINARY_DIR}/castConfigVersion.cmake"
  "${CMAKE_CURRENT_SOURCE_DIR}/cmake/CastProtobuf.cmake" DESTINATION "${CAST_CMAKE_DIR}")

# pkg-config: relocatable (the prefix is found from the file's own place), and what to link
# depends on the kind of library: a static one brings its private dependencies along.
file(RELATIVE_PATH CAST_PC_TO_PREFIX "/prefix/${CMAKE_INSTALL_LIBDIR}/pkgconfig" "/prefix")
string(REGEX REPLACE "/$" "" CAST_PC_TO_PREFIX "${CAST_PC_TO_PREFIX}")
if(BUILD_SHARED_LIBS)
  set(CAST_PC_LIBS "-lcast_client")
  set(CAST_PC_REQUIRES "protobuf")
  set(CAST_PC_REQUIRES_PRIVATE "Requires.private: grpc++ libcrypto")
else()
  set(CAST_PC_LIBS "-lcast_client -lcast_v1_proto -pthread")
  set(CAST_PC_REQUIRES "protobuf grpc++ libcrypto")
  set(CAST_PC_REQUIRES_PRIVATE "")
endif()
configure_file("${CMAKE_CURRENT_SOURCE_DIR}/cmake/cast.pc.in" "${CMAKE_CURRENT_BINARY_DIR}/cast.pc" @ONLY)
install(FILES "${CMAKE_CURRENT_BINARY_DIR}/cast.pc" DESTINATION "${CMAKE_INSTALL_LIBDIR}/pkgconfig")
