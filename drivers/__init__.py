"""Device sources (OAK/DepthAI camera and IMU, OpenCV cameras, serial GNSS/INS heading).

Every driver yields :class:`rig.types.Frame`. Device SDKs are imported inside the driver that
needs them, never here, so ``import drivers`` works on any machine.
"""
