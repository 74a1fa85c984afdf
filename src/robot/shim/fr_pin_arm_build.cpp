// Construction / destruction of the 7-DoF arm model (allocates; never called in the loop).
#include "fr_pin_arm_impl.hpp"

#include <cmath>
#include <cstdio>
#include <exception>
#include <stdexcept>
#include <string>

namespace
{
  using pinocchio::SE3;
  using Eigen::Matrix3d;
  using Eigen::Quaterniond;
  using Eigen::Vector3d;

  void set_err(char * err, int err_len, const char * msg)
  {
    if (err && err_len > 0)
      std::snprintf(err, static_cast<size_t>(err_len), "%s", msg);
  }

  bool all_finite(const double * p, int n)
  {
    for (int i = 0; i < n; ++i)
      if (!std::isfinite(p[i]))
        return false;
    return true;
  }

  Quaterniond unit_quat(const double * wxyz, const char * what)
  {
    Quaterniond qt(wxyz[0], wxyz[1], wxyz[2], wxyz[3]);  // Eigen ctor order is (w, x, y, z)
    const double n = qt.norm();
    if (!(n > 1e-12))
      throw std::runtime_error(std::string("zero quaternion in ") + what);
    qt.coeffs() /= n;
    return qt;
  }

  pinocchio::JointModel revolute(const double * a, int i)
  {
    Vector3d axis(a[0], a[1], a[2]);
    const double n = axis.norm();
    if (!(n > 1e-12))
      throw std::runtime_error("zero joint axis for joint " + std::to_string(i));
    axis /= n;
    const double tol = 1e-12;
    if ((axis - Vector3d::UnitZ()).norm() < tol)
      return pinocchio::JointModelRZ();
    if ((axis - Vector3d::UnitY()).norm() < tol)
      return pinocchio::JointModelRY();
    if ((axis - Vector3d::UnitX()).norm() < tol)
      return pinocchio::JointModelRX();
    return pinocchio::JointModelRevoluteUnaligned(axis);
  }
} // namespace

extern "C" FrPinArm * fr_pin_arm_new(
  const double * parent_pos,
  const double * parent_quat_wxyz,
  const double * axis,
  const double * mass,
  const double * com,
  const double * inertia,
  const double * armature,
  const double * tcp_pos,
  const double * tcp_quat_wxyz,
  const double * gravity,
  char * err,
  int err_len)
{
  constexpr int N = FR_PIN_ARM_NDOF;
  try
  {
    if (!parent_pos || !parent_quat_wxyz || !axis || !mass || !com || !inertia
        || !tcp_pos || !tcp_quat_wxyz || !gravity)
      throw std::runtime_error("null input pointer");
    if (!all_finite(parent_pos, 3 * N) || !all_finite(parent_quat_wxyz, 4 * N)
        || !all_finite(axis, 3 * N) || !all_finite(mass, N) || !all_finite(com, 3 * N)
        || !all_finite(inertia, 9 * N)
        || (armature && !all_finite(armature, N)) || !all_finite(tcp_pos, 3)
        || !all_finite(tcp_quat_wxyz, 4) || !all_finite(gravity, 3))
      throw std::runtime_error("non-finite input");

    auto * arm = new FrPinArm();
    try
    {
      pinocchio::Model & model = arm->model;
      model.name = "fr_arm7";
      model.gravity.linear(Vector3d(gravity[0], gravity[1], gravity[2]));
      model.gravity.angular().setZero();

      pinocchio::JointIndex parent = 0;
      for (int i = 0; i < N; ++i)
      {
        if (!(mass[i] >= 0.0))
          throw std::runtime_error("negative mass for body " + std::to_string(i));
        for (int k = 0; k < 3; ++k)
          if (!(inertia[9 * i + 4 * k] >= 0.0))
            throw std::runtime_error("negative moment of inertia for body " + std::to_string(i));

        const Quaterniond qp = unit_quat(parent_quat_wxyz + 4 * i, "parent_quat");
        const SE3 placement(qp.toRotationMatrix(), Vector3d::Map(parent_pos + 3 * i));
        const std::string jname = "joint" + std::to_string(i + 1);
        const pinocchio::JointIndex jid =
          model.addJoint(parent, revolute(axis + 3 * i, i), placement, jname);
        model.addJointFrame(jid);

        // Rotational inertia about the CoM, body frame (symmetrised against rounding).
        Matrix3d Ic = Eigen::Map<const Matrix3d>(inertia + 9 * i);
        Ic = (0.5 * (Ic + Ic.transpose())).eval();  // eval: avoid transpose aliasing
        const pinocchio::Inertia Y(
          mass[i], Vector3d::Map(com + 3 * i), pinocchio::Symmetric3(Ic));
        model.appendBodyToJoint(jid, Y, SE3::Identity());
        model.addBodyFrame("body" + std::to_string(i + 1), jid);

        if (armature)
          model.armature[model.joints[jid].idx_v()] = armature[i];
        parent = jid;
      }

      arm->tcp_joint = parent;
      arm->tcp_placement = SE3(
        unit_quat(tcp_quat_wxyz, "tcp_quat").toRotationMatrix(), Vector3d::Map(tcp_pos));
      model.addFrame(pinocchio::Frame(
        "tcp", parent, model.getFrameId("body7"), arm->tcp_placement, pinocchio::OP_FRAME));

      if (model.nq != N || model.nv != N)
        throw std::runtime_error("unexpected model size");

      arm->data = pinocchio::Data(model);
      arm->jac.setZero(6, model.nv);
      arm->zero.setZero(model.nv);
      set_err(err, err_len, "");
      return arm;
    }
    catch (...)
    {
      delete arm;
      throw;
    }
  }
  catch (const std::exception & e)
  {
    set_err(err, err_len, e.what());
  }
  catch (...)
  {
    set_err(err, err_len, "unknown C++ exception");
  }
  return nullptr;
}

extern "C" void fr_pin_arm_free(FrPinArm * arm)
{
  delete arm;  // Model/Data destructors do not throw
}
