"""What every process agrees on: the robot description, errors and (later) the wire."""
