"""The ROS 2 shell: the only subpackage that imports rclpy (in `guidance_node`, `sim_node` and
`adapters`; `env` only prepares environments and imports no ROS module)."""
