"""The run folder: its layout (the only module that spells a file name), atomic writes, the
lock, artefacts, PLY clouds, the ingest store."""
