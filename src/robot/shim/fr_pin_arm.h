/* Minimal C ABI over Pinocchio 4.1 for a 7-DoF serial arm built from arrays.
 * All matrices are column-major. "root" = the frame body 0 is attached to. */
#ifndef FR_PIN_ARM_H
#define FR_PIN_ARM_H
#ifdef __cplusplus
extern "C" {
#endif

#define FR_PIN_ARM_NDOF 7

typedef struct FrPinArm FrPinArm;

/* Body i (0..6) hangs off body i-1 (root for i = 0) through a revolute joint
 * located at body i's origin (MuJoCo jnt_pos = 0).
 *   parent_pos[7*3], parent_quat_wxyz[7*4]  body i frame in parent frame (body_pos / body_quat,
 *                                           quats need not be normalised)
 *   axis[7*3]                               joint axis in body i frame (jnt_axis, any length > 0)
 *   mass[7], com[7*3]                       body mass and CoM in body frame (body_mass / body_ipos)
 *   inertia[7*9]                            3x3 rotational inertia about the CoM in the body frame,
 *                                           column-major (symmetric)
 *   armature[7]                             rotor inertia added to M's diagonal (dof_armature); may be NULL
 *   tcp_pos[3], tcp_quat_wxyz[4]            TCP frame in body 6 frame
 *   gravity[3]                              gravity in the root frame, e.g. {0,0,-9.81}
 * Returns NULL on failure with a message in err (if err != NULL && err_len > 0). */
FrPinArm* fr_pin_arm_new(const double* parent_pos, const double* parent_quat_wxyz,
                         const double* axis, const double* mass, const double* com,
                         const double* inertia,
                         const double* armature, const double* tcp_pos,
                         const double* tcp_quat_wxyz, const double* gravity, char* err,
                         int err_len);

void fr_pin_arm_free(FrPinArm* arm);

/* Full set, allocation-free. Outputs (any may NOT be NULL):
 *   tcp_pos[3], tcp_rot[9]   TCP pose in root frame (rotation column-major)
 *   jac[42]                  6x7 TCP Jacobian, LOCAL_WORLD_ALIGNED, rows = (v_lin; omega)
 *   jdot_qdot[6]             classical TCP acceleration at ddq = 0, LOCAL_WORLD_ALIGNED (lin; ang)
 *   mass[49]                 7x7 joint-space inertia (symmetric, incl. armature)
 *   coriolis[7]              C(q,dq) dq
 *   gravity[7]               g(q)  (so that tau = M ddq + coriolis + gravity)
 * Returns 0 on success, nonzero on failure (never throws). */
int fr_pin_arm_compute(FrPinArm* arm, const double* q, const double* dq, double* tcp_pos,
                       double* tcp_rot, double* jac, double* jdot_qdot, double* mass,
                       double* coriolis, double* gravity);

/* The TCP's task quantities only (for a reference state): pose, Jacobian and J̇q̇, as in
 * fr_pin_arm_compute, without the dynamics. */
int fr_pin_arm_task(FrPinArm* arm, const double* q, const double* dq, double* tcp_pos,
                    double* tcp_rot, double* jac, double* jdot_qdot);

/* Cheap path for IK: TCP pose and 6x7 LOCAL_WORLD_ALIGNED Jacobian only. */
int fr_pin_arm_fk_jac(FrPinArm* arm, const double* q, double* tcp_pos, double* tcp_rot,
                      double* jac);

#ifdef __cplusplus
}
#endif
#endif
