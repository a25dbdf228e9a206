"""Where the receiver daemon's poses go: UDP pose packets (``udp``), MAVLink to a flight controller
(``mavlink/``), ROS 2 topics and the MCAP flight log (``ros/``)."""
