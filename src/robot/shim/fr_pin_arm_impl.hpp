// Internal: the opaque FrPinArm struct shared by the shim's translation units.
#pragma once
#include "pinocchio/multibody.hpp"

#include "fr_pin_arm.h"

struct FrPinArm
{
  pinocchio::Model model;
  pinocchio::Data data;
  pinocchio::JointIndex tcp_joint = 0;
  pinocchio::SE3 tcp_placement = pinocchio::SE3::Identity();  // TCP in tcp_joint's frame
  pinocchio::Data::Matrix6x jac;                                // preallocated 6 x nv
  Eigen::VectorXd zero;                                         // nv zeros (ddq = 0)
};
