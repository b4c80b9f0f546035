"""keo: a real-time Kinematic Error Observer for industrial robots.

The math lives in `kinematics`, `observer` and `timing` (no I/O); `pipeline` joins them;
`service`, `bus` and the adapters only move data.
"""

__version__ = "0.1.0"
