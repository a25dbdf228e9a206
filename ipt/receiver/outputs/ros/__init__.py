"""ROS 2 over CycloneDDS without a ROS installation: a frame's messages (``frames``), the DDS writer
(``dds``), the MCAP flight log (``record``), the loopback-only DDS settings (``ddsconfig``) and the
daemon's output (``output``)."""
