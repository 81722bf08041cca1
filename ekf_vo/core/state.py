"""Layout of the camera state vector x (13): named slices instead of magic numbers.

    POS  r^W   camera centre in the world frame                     [m]
    QUAT q^WC  orientation, Hamilton wxyz, camera -> world rotation  [-]
    VEL  v^W   linear velocity in the world frame                   [m/s]
    ANG  w^C   angular velocity in the camera frame                 [rad/s]

A joint state (in-filter points, docs/method.md §8) appends one inverse depth per point
after these 13 entries.
"""
POS = slice(0, 3)
QUAT = slice(3, 7)
VEL = slice(7, 10)
ANG = slice(10, 13)
STATE_DIM = 13
#: the part of the state the observation depends on (position and quaternion)
POSE = slice(0, 7)
