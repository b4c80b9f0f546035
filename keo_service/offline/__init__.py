"""The offline commands' pipelines: read a recording once, pair the streams, run a pipeline
over them, and hand back what the command writes or prints.

`recording` reads both streams of a recording (interchange CSV or ROS 2 MCAP) once per command
and builds the cell they are interpreted with; `estimate` is `keo estimate` (the batch path,
falling back to the streaming estimator), `delay` is `keo calibrate-delay` and `analyze` is
`keo analyze`. The file formats stay in `keo_service.io`, the math in `keo_service.fit` and
`keo_service.core`; the CLI only parses arguments and prints. No network, no asyncio.
"""
