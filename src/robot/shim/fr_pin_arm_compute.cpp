// Per-cycle computations. Allocation-free: q/dq are wrapped by Eigen::Map (bound to the library's
// Eigen::Ref<const VectorXd> explicit instantiations) and all outputs live in Data / FrPinArm.
#include "fr_pin_arm_impl.hpp"

#include "pinocchio/algorithm/compute-all-terms.hpp"
#include "pinocchio/algorithm/frames.hpp"
#include "pinocchio/algorithm/jacobian.hpp"
#include "pinocchio/algorithm/kinematics.hpp"

#include <cmath>
#include <cstring>

namespace
{
  constexpr int N = FR_PIN_ARM_NDOF;
  using ConstVecMap = Eigen::Map<const Eigen::VectorXd>;

  bool all_finite(const double * p, int n)
  {
    for (int i = 0; i < n; ++i)
      if (!std::isfinite(p[i]))
        return false;
    return true;
  }

  // Pose + LOCAL_WORLD_ALIGNED Jacobian of the TCP from data.oMi and data.J.
  void write_pose_jac(FrPinArm & arm, double * tcp_pos, double * tcp_rot, double * jac)
  {
    const pinocchio::SE3 oMtcp = arm.data.oMi[arm.tcp_joint] * arm.tcp_placement;
    Eigen::Map<Eigen::Vector3d> pos_out(tcp_pos);
    Eigen::Map<Eigen::Matrix3d> rot_out(tcp_rot);  // column-major
    pos_out = oMtcp.translation();
    rot_out = oMtcp.rotation();
    pinocchio::getFrameJacobian(
      arm.model, arm.data, arm.tcp_joint, arm.tcp_placement, pinocchio::LOCAL_WORLD_ALIGNED,
      arm.jac);
    std::memcpy(jac, arm.jac.data(), sizeof(double) * 6 * N);  // Matrix6x is column-major
  }
} // namespace

extern "C" int fr_pin_arm_compute(
  FrPinArm * arm,
  const double * q,
  const double * dq,
  double * tcp_pos,
  double * tcp_rot,
  double * jac,
  double * jdot_qdot,
  double * mass,
  double * coriolis,
  double * gravity)
{
  if (!arm || !q || !dq || !tcp_pos || !tcp_rot || !jac || !jdot_qdot || !mass || !coriolis
      || !gravity)
    return 1;
  if (!all_finite(q, N) || !all_finite(dq, N))
    return 2;
  try
  {
    pinocchio::Data & data = arm->data;
    // One pass: oMi, v, a (= bias, ddq = 0), J, M (upper), nle, g (+ com, centroidal, energy).
    pinocchio::computeAllTerms(arm->model, data, ConstVecMap(q, N), ConstVecMap(dq, N));

    write_pose_jac(*arm, tcp_pos, tcp_rot, jac);

    const pinocchio::Motion a = pinocchio::getFrameClassicalAcceleration(
      arm->model, data, arm->tcp_joint, arm->tcp_placement, pinocchio::LOCAL_WORLD_ALIGNED);
    Eigen::Map<Eigen::Matrix<double, 6, 1>> jdq_out(jdot_qdot);
    jdq_out = a.toVector();  // (linear; angular)

    data.M.triangularView<Eigen::StrictlyLower>() =
      data.M.transpose().triangularView<Eigen::StrictlyLower>();
    std::memcpy(mass, data.M.data(), sizeof(double) * N * N);

    Eigen::Map<Eigen::Matrix<double, N, 1>> c_out(coriolis), g_out(gravity);
    c_out = data.nle - data.g;
    g_out = data.g;
    return 0;
  }
  catch (...)
  {
    return 3;
  }
}

extern "C" int fr_pin_arm_fk_jac(
  FrPinArm * arm, const double * q, double * tcp_pos, double * tcp_rot, double * jac)
{
  if (!arm || !q || !tcp_pos || !tcp_rot || !jac)
    return 1;
  if (!all_finite(q, N))
    return 2;
  try
  {
    pinocchio::computeJointJacobians(arm->model, arm->data, ConstVecMap(q, N));  // oMi + J
    write_pose_jac(*arm, tcp_pos, tcp_rot, jac);
    return 0;
  }
  catch (...)
  {
    return 3;
  }
}

extern "C" int fr_pin_arm_task(
  FrPinArm * arm, const double * q, const double * dq, double * tcp_pos, double * tcp_rot,
  double * jac, double * jdot_qdot)
{
  if (!arm || !q || !dq || !tcp_pos || !tcp_rot || !jac || !jdot_qdot)
    return 1;
  if (!all_finite(q, N) || !all_finite(dq, N))
    return 2;
  try
  {
    // Placements, velocities and bias accelerations (ddq = 0), then the Jacobian from them.
    pinocchio::forwardKinematics(arm->model, arm->data, ConstVecMap(q, N), ConstVecMap(dq, N), arm->zero);
    pinocchio::computeJointJacobians(arm->model, arm->data);
    write_pose_jac(*arm, tcp_pos, tcp_rot, jac);
    const pinocchio::Motion a = pinocchio::getFrameClassicalAcceleration(
      arm->model, arm->data, arm->tcp_joint, arm->tcp_placement, pinocchio::LOCAL_WORLD_ALIGNED);
    Eigen::Map<Eigen::Matrix<double, 6, 1>> jdq_out(jdot_qdot);
    jdq_out = a.toVector();
    return 0;
  }
  catch (...)
  {
    return 3;
  }
}
