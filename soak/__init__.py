"""``scara-soak``: the robot as a service, disturbed at random while it runs task after task,
and an independent checker of its recordings (``docs/soak.md``)."""
