"""The ROS 2 shell: the only subpackage that imports rclpy (in the guidance node's modules,
`guidance_node`, `node_base` and `managed_node`, in `sim_node` and `adapters`; `env` only
prepares environments and imports no ROS module)."""
