"""MAVLink to the flight controller: the frames' maths (``frames``), the sans-IO session (``session``),
the serial and UDP links (``links``) and the daemon's output (``output``)."""
