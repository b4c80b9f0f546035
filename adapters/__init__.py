"""Device adapters: bytes in, typed samples out, one class per wire format.

`simple_message` and `line_protocol` are pure codecs (no sockets); `encoder` and `tracker`
move bytes between a device's TCP connection and the codecs and publish samples on Zenoh;
`mock_devices` are TCP servers that speak the same wire formats from a simulated scenario.
"""
