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
// carries the version it was built against and robot_sim.kinematics checks it.

#include <pinocchio/multibody.hpp>
#include <pinocchio/algorithm/compute-all-terms.hpp>
#include <pinocchio/algorithm/frames.hpp>

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

BOOST_PYTHON_MODULE(_pinocchio_inplace) {
  // Pinocchio's module registers the Model/Data classes and eigenpy's converters
  bp::import("pinocchio");
  bp::scope().attr("PINOCCHIO_VERSION") = PINOCCHIO_VERSION;
  bp::def("compute_all_terms", &compute_all_terms,
          (bp::arg("model"), bp::arg("data"), bp::arg("q"), bp::arg("v")),
          "computeAllTerms(model, data, q, v) and updateFramePlacements(model, data), "
          "with M symmetrised; q and v are read in place when contiguous float64.");
}
