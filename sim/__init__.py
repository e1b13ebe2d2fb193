"""What serves both sides of the wire: the in-process simulation, the measures of a run, the
figure, and the commands that run and report scenarios (``scara-sim``, ``scara-run``,
``scara-report``)."""
