"""The math: frames and kinematics, the observer, timing, the estimator, corrections and the
vectorised chain. Imports only numpy, scipy, pinocchio and the standard library: no asyncio,
zenoh, msgspec, rerun or matplotlib, and nothing of keo outside this package."""
