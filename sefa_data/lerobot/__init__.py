"""LeRobot datasets (v3.0 layout) in and out: the layout and its checks (`layout`), the reader
(`reader`), the writer `sefa convert` runs (`writer`, with its statistics `stats` and the video
encoder that cannot hang a command, `video_encoder`), and the conversion itself (`convert`)."""
