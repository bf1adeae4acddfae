"""The run report in layers, each feeding the next (the stage shell: stages/report.py).

  gather.py   read the run folder (io/run/artefacts.py, io/run/ingest_store.py) ->
              RunData, CloudView
  metrics.py  pure numbers: per-frame rows, the summary, residuals, quality, noise -> Metrics
  figures.py  every figure drawn first, as tasks on an executor (report/plots.py) -> {name: PNG}
  page.py     the HTML composed last from all of the above (report/html.py)
"""
