# Builds msgs/ (minflow_msgs) against the ROS 2 wheels from PyPI (tests/python/ros2_env.sh):
# cmake -DCMAKE_PROJECT_INCLUDE=<this file>. The wheels' exported CMake targets of their
# Python bindings name the include folders of the machine that built them
# (/opt/python/cp3XX-cp3XX/include/python3.X and its numpy); this rewrites them to this
# interpreter's once the project's CMakeLists.txt has been read, before generation.
find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module)
execute_process(
  COMMAND "${Python3_EXECUTABLE}" -c "import numpy; print(numpy.get_include())"
  OUTPUT_VARIABLE _minflow_numpy_include OUTPUT_STRIP_TRAILING_WHITESPACE)

function(_minflow_fix_wheel_paths)
  get_directory_property(_targets DIRECTORY "${CMAKE_SOURCE_DIR}" IMPORTED_TARGETS)
  foreach(_target IN LISTS _targets)
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    list(TRANSFORM _dirs REPLACE "^/opt/python/[^/]+/lib/python[0-9.]+/site-packages/numpy/.*$"
      "${_minflow_numpy_include}")
    list(TRANSFORM _dirs REPLACE "^/opt/python/[^/]+/include/python[0-9.]+$"
      "${Python3_INCLUDE_DIRS}")
    set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_dirs}")
  endforeach()
endfunction()

cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _minflow_fix_wheel_paths)
