"""The ROS 2 nodes of the actuator graph (thin: numerics live in physics and surrogates)."""
