"""AprilTag detection: the C library's binding and the helper process that runs it, replaced before its leak matters."""
