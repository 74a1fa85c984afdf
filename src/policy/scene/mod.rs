//! What the policy sees, without any network: the observation (camera views, proprioception,
//! instruction), rotations (6D <-> matrix <-> quaternion), depth lifted to world points, the
//! workspace normalisation, farthest point sampling, the Dynamic Radius Schedule that picks the
//! geometric tokens, and the order of point tokens in the scan. No candle here.
pub mod farthest_point;
pub mod lifting;
pub mod observation;
pub mod radius_schedule;
pub mod rotation;
pub mod token_order;
pub mod workspace;
