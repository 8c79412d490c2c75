// A float64 written as JSON text the way orjson writes it, for a compiled caller (a numba
// kernel that writes a message's bytes from arrays).  The recordings hold orjson's bytes
// (services.runtime.messages.dumps); a message written here must be the same bytes.
//
// orjson writes the shortest digits that read back as the same double (what Python's repr
// gives), in fixed notation when 1e-5 <= |x| < 1e16 ("0.00001", "123.0",
// "9999999999999998.0") and in exponent notation otherwise, without padding the exponent
// ("1e-6", "1.5e+16", "5e-324").  C++17's std::to_chars gives the same shortest digits;
// the layout is done here.  Checked against orjson on random bit patterns and the
// boundaries (tests/kernel_plumbing/test_json_numbers.py, bench/json_numbers.py).
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstring>

extern "C" {

// x written into out (at least 32 bytes); the number of bytes, or -1 for NaN and infinity
// (JSON has no such numbers: the caller takes its checked path, which says which field).
int kernel_plumbing_json_double(double x, char *out) {
  if (!std::isfinite(x)) return -1;
  char *o = out;
  if (std::signbit(x)) *o++ = '-';
  if (x == 0.0) {
    std::memcpy(o, "0.0", 3);
    return static_cast<int>(o - out) + 3;
  }
  char sci[40];
  auto r = std::to_chars(sci, sci + sizeof sci, std::fabs(x), std::chars_format::scientific);
  // sci: d[.ddd]e(+|-)XX
  char digits[20];
  int n = 0;
  const char *p = sci;
  for (; p < r.ptr && *p != 'e'; ++p)
    if (*p != '.') digits[n++] = *p;
  int exponent = 0;
  bool negative = false;
  for (++p; p < r.ptr; ++p) {
    if (*p == '-') negative = true;
    else if (*p != '+') exponent = exponent * 10 + (*p - '0');
  }
  if (negative) exponent = -exponent;
  const int point = exponent + 1;  // digits before the decimal point
  if (-5 < point && point <= 16) {
    if (point <= 0) {
      *o++ = '0';
      *o++ = '.';
      for (int i = 0; i < -point; ++i) *o++ = '0';
      std::memcpy(o, digits, n);
      o += n;
    } else if (point >= n) {
      std::memcpy(o, digits, n);
      o += n;
      for (int i = n; i < point; ++i) *o++ = '0';
      *o++ = '.';
      *o++ = '0';
    } else {
      std::memcpy(o, digits, point);
      o += point;
      *o++ = '.';
      std::memcpy(o, digits + point, n - point);
      o += n - point;
    }
  } else {
    *o++ = digits[0];
    if (n > 1) {
      *o++ = '.';
      std::memcpy(o, digits + 1, n - 1);
      o += n - 1;
    }
    *o++ = 'e';
    *o++ = exponent < 0 ? '-' : '+';
    auto e = std::to_chars(o, o + 4, exponent < 0 ? -exponent : exponent);
    o = e.ptr;
  }
  return static_cast<int>(o - out);
}

}  // extern "C"

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_json_numbers",
    "JSON_DOUBLE: the address of int (double x, char *out), x as orjson writes it (json_numbers.cpp).",
    -1, nullptr,
};

PyMODINIT_FUNC PyInit__json_numbers(void) {
  PyObject *m = PyModule_Create(&module);
  if (m == nullptr) return nullptr;
  if (PyModule_AddObject(m, "JSON_DOUBLE",
                         PyLong_FromUnsignedLongLong(reinterpret_cast<std::uintptr_t>(&kernel_plumbing_json_double))) < 0) {
    Py_DECREF(m);
    return nullptr;
  }
  return m;
}
