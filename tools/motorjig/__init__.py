"""MotorJig host side: bus-master library, jigctl command line and the virtual bench."""
