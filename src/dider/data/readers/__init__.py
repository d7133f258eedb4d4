"""Readers of the file formats dider knows: each module holds a source class that a data config's
``data.source._target_`` names (:mod:`dider.targets` builds it; its fields are the node's other keys).

- Track formats (:class:`~dider.data.track_sources.TrackFile`: ``read(path)`` gives one long track table, a
  DataFrame with the columns agent, frame, x, y and optionally scene, vx, vy, agent_class, which ``data=table``'s
  windows, split and normaliser then take): :mod:`.eth_ucy`. :mod:`.kloppy` reads a soccer provider's files into
  the same rows (:class:`~dider.data.track_sources.KloppySource`, ``data=soccer``).
- Clip formats (:class:`~dider.data.clip_source.ClipSource`: clips already cut to a fixed length, raw, as
  :class:`~dider.data.clip_source.Clips`): :mod:`.nri_files`, :mod:`.dnri_files`, :mod:`.basketball`,
  :mod:`.trajectories` (``.npz``). The simulators are clip sources too, in :mod:`dider.data.simulators`.

A new format needs no module here: its class may live in the user's own package, named by its ``_target_``.
"""
