"""Device adapters (installed as `keo_service.adapters`): bytes in, typed samples out, one
codec per wire format, connections apart from codecs.

Codecs, pure (no sockets): `simple_message` (MotoROS), `line_protocol` (keo's tracker lines),
`rtde` (Universal Robots), `kuka_rsi` (KUKA RSI XML), `abb_egm` (ABB EGM, protobuf from
`egm/egm.proto`). Connections: `connection` (the reconnecting TCP loop), `health` (what a user
sees of an adapter), `realtime` (best-effort real-time priority for the UDP answers).
Adapters, which join a connection, a codec and the bus: `devices` (TCP and ROS 2),
`udp_devices` (RSI, EGM); `select` turns the protocol table's rows (`io.protocols`) into them.
Mock devices speaking the same wire formats: `mock` (what they share: `MockDevice`,
`MockSettings`, `build_mock`), `mock_devices` (TCP), `mock_udp` (RSI, EGM controllers),
`mock_ros2` (ROS 2 drivers).
"""
