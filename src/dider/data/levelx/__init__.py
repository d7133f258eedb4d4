"""Reading the levelXdata road-user data sets (inD, rounD, uniD: one schema) from their raw CSV files.

Each recording is three files, XX_tracks.csv (one row per track and frame), XX_tracksMeta.csv (one row
per track) and XX_recordingMeta.csv (one row). The modules, in the order the data pass through them:
:mod:`~dider.data.levelx.recordings` finds the recordings,
:mod:`~dider.data.levelx.reading` reads and validates the CSV files, :mod:`~dider.data.levelx.windows`
cuts a recording into packed windows, :mod:`~dider.data.levelx.tracks` caches them and
:mod:`~dider.data.levelx.source` is the data config's ``source`` node. The DataModule that splits and serves them is
:class:`dider.data.tracks.TracksDataModule`.
"""
