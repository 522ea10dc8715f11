// Python glue shared by the compiled modules: run C++ without the GIL, turning a C++
// exception into a Python one. Include after Python.h.
#pragma once

#include <new>
#include <stdexcept>
#include <string>

namespace rs {

// Runs fn without the GIL; a C++ exception becomes a Python one. False: error set.
template <class Fn>
bool run_released(Fn&& fn) {
  std::string message;
  bool out_of_memory = false;
  Py_BEGIN_ALLOW_THREADS
  try {
    fn();
  } catch (const std::bad_alloc&) {
    out_of_memory = true;
  } catch (const std::exception& e) {
    message = e.what();
    if (message.empty()) message = "C++ exception";
  } catch (...) {
    message = "unknown C++ exception";
  }
  Py_END_ALLOW_THREADS
  if (out_of_memory) {
    PyErr_NoMemory();
    return false;
  }
  if (!message.empty()) {
    PyErr_SetString(PyExc_RuntimeError, message.c_str());
    return false;
  }
  return true;
}

}  // namespace rs
