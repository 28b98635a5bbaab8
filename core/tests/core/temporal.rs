//! Temporal state: reprojection with motion vectors and with depth + cameras,
//! validity masks, scene-cut detection.
