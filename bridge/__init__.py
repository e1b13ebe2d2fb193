"""The Zenoh bridge (``scara-bridge``) and the terminal monitor (``scara-monitor``): the robot's
state on a Zenoh network, and the operator's commands back to it."""
