"""The simulators: clip sources whose clips are generated, not read (``data=synth``: :mod:`.push`; ``data=springs``
and ``data=charged``: :mod:`.particles`). Each module holds the simulation, vectorised over clips, and its source:
the frozen dataclass a data config's ``data.source._target_`` names, whose fields are what the simulation depends
on. A split's clips are generated from its own seed and cached under the data's cache folder by every setting that
made them (``data.num_*`` are the sizes to generate: ``GENERATED``)."""
