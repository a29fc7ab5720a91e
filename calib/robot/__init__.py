"""The robot: its model file, kinematics, transforms, URDF/DH conversion, gravity, controller values."""
