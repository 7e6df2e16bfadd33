"""Recordings in: one reader per format (ROS 1/2 bags and MCAP: `ros`, with the topic map, field
selectors, TF lookups, camera decoding and time alignment it uses; HDF5: `hdf5`; Diffusion
Policy Zarr: `dp_zarr`), each yielding `sefa_data.episode` Episodes for the store. The LeRobot
reader is in `sefa_data.lerobot`. Nothing is imported here: a reader's libraries (rosbags, h5py)
load only when that format is read."""
