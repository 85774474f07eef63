# Passed as -DCMAKE_PROJECT_INCLUDE=... when building a message package against the PyPI ROS
# wheels. Their exported <pkg>::<pkg>__rosidl_generator_py targets carry the wheel builder's
# Python and numpy include paths (/opt/python/...), which do not exist here, and CMake refuses
# to generate ("Imported target ... includes non-existent path"). At the end of configuration
# (cmake_language DEFER) every such target's missing include directories are replaced by this
# interpreter's Python and numpy headers.
cmake_minimum_required(VERSION 3.21)

function(_maem_fix_wheel_include_dirs)
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
  get_property(_targets DIRECTORY "${CMAKE_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
  foreach(_target IN LISTS _targets)
    if(NOT _target MATCHES "__rosidl_generator_py$")
      continue()
    endif()
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_fixed "")
    set(_changed FALSE)
    foreach(_dir IN LISTS _dirs)
      if(_dir MATCHES "^\\$<" OR EXISTS "${_dir}")
        list(APPEND _fixed "${_dir}")
      else()
        set(_changed TRUE)
      endif()
    endforeach()
    if(_changed)
      list(APPEND _fixed ${Python3_INCLUDE_DIRS} ${Python3_NumPy_INCLUDE_DIRS})
      list(REMOVE_DUPLICATES _fixed)
      set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_fixed}")
      message(STATUS "maem_ros: ${_target} include dirs -> local Python/numpy headers")
    endif()
  endforeach()
endfunction()

cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _maem_fix_wheel_include_dirs)
