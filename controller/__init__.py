"""The control law (planner, behaviours, coordinators), the controller node, its service and
the ``controller`` command."""
