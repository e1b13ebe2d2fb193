"""The control law (planner, behaviours, coordinators) and the controller node."""
