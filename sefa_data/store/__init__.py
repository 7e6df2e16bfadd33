"""The episode store (`zarr_store.EpisodeStore`): a Diffusion-Policy-layout Zarr written by
transactional appends (`journal`: the undo journal, the write lock, fault points), checked by
checksums (`integrity`), and summarized for `sefa inspect` (`inspect`)."""
