"""Maps: cutting a prior map into blocks or tiles, storing them, and serving the local map.

- :mod:`blockloc.maps.pcd`: ``read_pcd`` / ``write_pcd`` (binary PCD, x y z intensity float32).
- :mod:`blockloc.maps.files`: ``MapFiles`` / ``open_map_files`` (a local directory or a URL).
- :mod:`blockloc.maps.store`: ``open_map(path) -> MapStore``, ``MapWriter`` (atomic builds).
- :mod:`blockloc.maps.block_maps`: block maps (Feng et al., Algorithm 1).
- :mod:`blockloc.maps.grid_tiles`: grid-puzzle tiles (Byeon et al., Algorithms 1 and 2).
- :mod:`blockloc.maps.policies`: block / grid / SRT-PM / global region policies, ``make_policy``.
- :mod:`blockloc.maps.provider`: ``MapProvider`` (pose in, local map out, prefetching).
- :mod:`blockloc.maps.summary`, :mod:`blockloc.maps.plot`: what a store holds, drawn from above.
- :mod:`blockloc.maps.remote`, :mod:`blockloc.maps.server`: stores over HTTP(S) and S3.
"""
