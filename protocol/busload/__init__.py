"""Worst-case CAN bus load of the wire: :mod:`.load` computes it from the DBC, :mod:`.bound`
gives the least load any layout could reach, :mod:`.report` is ``scara-busload``."""
