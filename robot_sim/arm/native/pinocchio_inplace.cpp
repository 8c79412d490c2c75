// The KRC's per-cycle Pinocchio update without a heap allocation.
//
// Pinocchio's Python bindings take their vector arguments as `const VectorXd &`,
// so eigenpy copies every numpy argument into a new Eigen vector: two 56 B
// mallocs per call of computeAllTerms(q, v), once per 1 ms control step.  Here
// the same algorithms take `Eigen::Ref<const VectorXd>`, which eigenpy maps onto
// the numpy buffer when it is contiguous float64 (and copies otherwise, like the
// bindings).  Model and Data are the Python objects' own (boost.python passes
// references), so the results land where `ArmKinematics.views` already looks.
//
// Compiled by setup.py against the headers of the pin wheel it builds with; the
// layout of Model and Data must be that of the loaded Pinocchio, so the module
// carries the version it was built against and robot_sim.arm.kinematics checks it.

#include <cstdint>
#include <stdexcept>

#include <pinocchio/multibody.hpp>
#include <pinocchio/algorithm/compute-all-terms.hpp>
#include <pinocchio/algorithm/frames.hpp>
#include <pinocchio/spatial.hpp>

#include <eigenpy/eigenpy.hpp>

#include <boost/python.hpp>

namespace bp = boost::python;

typedef Eigen::Ref<const Eigen::VectorXd> ConstVectorRef;

// What pinocchio.computeAllTerms followed by pinocchio.updateFramePlacements
// leaves in data, bit for bit: the binding also mirrors the CRBA's upper
// triangle of M into the lower one.
static void compute_all_terms(const pinocchio::Model &model, pinocchio::Data &data,
                              const ConstVectorRef &q, const ConstVectorRef &v) {
  pinocchio::computeAllTerms(model, data, q, v);
  data.M.triangularView<Eigen::StrictlyLower>() =
      data.M.transpose().triangularView<Eigen::StrictlyLower>();
  pinocchio::updateFramePlacements(model, data);
}

// a C-contiguous (6, nv) numpy array, seen by eigenpy through its transpose: a
// column-major (nv, 6) matrix (eigenpy maps column-major Refs in place)
typedef Eigen::Ref<Eigen::MatrixXd> TransposedJacobianRef;

// What the measurement of a cycle asks of Pinocchio, in one call, bit for bit: what
// pinocchio.forwardKinematics(q), computeJointJacobians(q) and updateFramePlacements
// leave in data, and what getFrameJacobian(frame, LOCAL) would return, written into J
// (6 x nv, a C-contiguous float64 array, passed as its transpose) instead of a new
// array.  Four calls through the bindings copied q three times and allocated the result.
static void measured_kinematics(const pinocchio::Model &model, pinocchio::Data &data,
                                const ConstVectorRef &q, pinocchio::FrameIndex frame,
                                TransposedJacobianRef JT) {
  if (JT.rows() != model.nv || JT.cols() != 6)
    throw std::invalid_argument("measured_kinematics: J must be a C-contiguous (6, nv) float64 array, "
                                "passed as J.T");
  pinocchio::forwardKinematics(model, data, q);
  pinocchio::computeJointJacobians(model, data, q);
  pinocchio::updateFramePlacements(model, data);
  auto J = JT.transpose();
  J.setZero();  // the binding's result starts at zero; columns outside the frame's support stay so
  pinocchio::getFrameJacobian(model, data, frame, pinocchio::LOCAL, J);
}

// The same two updates for a compiled caller (a numba kernel of the cell's cycle, which
// holds no Python object): Model and Data by address, vectors and the Jacobian as raw
// float64 buffers of the model's sizes.  C linkage, and no exception crosses it: a
// return of 0 is success, anything else a failure the caller reports.
extern "C" {

int robot_sim_compute_all_terms(const void *model, void *data, const double *q, const double *v) {
  try {
    const auto &m = *static_cast<const pinocchio::Model *>(model);
    Eigen::Map<const Eigen::VectorXd> qm(q, m.nq), vm(v, m.nv);
    compute_all_terms(m, *static_cast<pinocchio::Data *>(data), qm, vm);
    return 0;
  } catch (...) {
    return 1;
  }
}

int robot_sim_measured_kinematics(const void *model, void *data, const double *q, long frame, double *J) {
  try {
    const auto &m = *static_cast<const pinocchio::Model *>(model);
    Eigen::Map<const Eigen::VectorXd> qm(q, m.nq);
    Eigen::Map<Eigen::MatrixXd> JT(J, m.nv, 6);  // the C-contiguous (6, nv) array, column-major
    Eigen::Ref<Eigen::MatrixXd> ref(JT);
    measured_kinematics(m, *static_cast<pinocchio::Data *>(data), qm,
                        static_cast<pinocchio::FrameIndex>(frame), ref);
    return 0;
  } catch (...) {
    return 1;
  }
}

// pinocchio.log3 of a rotation given as 9 row-major numbers (what the bindings copy a
// numpy array into), into out (3): the teacher's hand in a kernel takes the same bits.
int robot_sim_log3(const double *R, double *out) {
  try {
    const Eigen::Matrix3d M = Eigen::Map<const Eigen::Matrix<double, 3, 3, Eigen::RowMajor>>(R);
    Eigen::Map<Eigen::Vector3d> result(out);
    result = pinocchio::log3(M);
    return 0;
  } catch (...) {
    return 1;
  }
}

}  // extern "C"

// Where the Python objects keep their C++ Model and Data, for the functions above.
static bp::tuple model_and_data(const pinocchio::Model &model, pinocchio::Data &data) {
  return bp::make_tuple(reinterpret_cast<std::uintptr_t>(&model), reinterpret_cast<std::uintptr_t>(&data));
}

BOOST_PYTHON_MODULE(_pinocchio_inplace) {
  // Pinocchio's module registers the Model/Data classes and eigenpy's converters
  bp::import("pinocchio");
  bp::scope().attr("PINOCCHIO_VERSION") = PINOCCHIO_VERSION;
  bp::def("compute_all_terms", &compute_all_terms,
          (bp::arg("model"), bp::arg("data"), bp::arg("q"), bp::arg("v")),
          "computeAllTerms(model, data, q, v) and updateFramePlacements(model, data), "
          "with M symmetrised; q and v are read in place when contiguous float64.");
  bp::def("measured_kinematics", &measured_kinematics,
          (bp::arg("model"), bp::arg("data"), bp::arg("q"), bp::arg("frame"), bp::arg("JT")),
          "forwardKinematics(model, data, q), computeJointJacobians(model, data, q), "
          "updateFramePlacements(model, data), and getFrameJacobian(model, data, frame, LOCAL) "
          "written into J, a C-contiguous (6, nv) float64 array passed as J.T.");
  bp::def("model_and_data", &model_and_data, (bp::arg("model"), bp::arg("data")),
          "(address of the C++ Model, address of the C++ Data) of these Python objects, for "
          "COMPUTE_ALL_TERMS and MEASURED_KINEMATICS; valid while the objects live.");
  // the C entry points' addresses: int (model, data, q, v) and int (model, data, q, frame, J)
  bp::scope().attr("COMPUTE_ALL_TERMS") = reinterpret_cast<std::uintptr_t>(&robot_sim_compute_all_terms);
  bp::scope().attr("MEASURED_KINEMATICS") = reinterpret_cast<std::uintptr_t>(&robot_sim_measured_kinematics);
  // int (R, out): pinocchio.log3 of 9 row-major numbers into 3
  bp::scope().attr("LOG3") = reinterpret_cast<std::uintptr_t>(&robot_sim_log3);
}
