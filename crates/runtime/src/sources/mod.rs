//! The sources: each turns an outside stream into model-form values at its
//! edge and offers them into its stream's feed (`streams`): the servo buses
//! (`dynamixel`), the head camera through V4L2 (`camera`), the ROS 2
//! subscriptions (`ros`) and an MCAP recording (`replay`).

pub mod camera;
pub mod dynamixel;
pub mod replay;
pub mod ros;
