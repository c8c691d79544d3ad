"""The NeRF: hash-grid fields, occupancy / proposal sampling, volume rendering, training,
checkpoints, evaluation and rendering. Entry points for other stages:

  training_run.train(dataset, run_dir, init_variables=None, steps=None, pixel_weights=None, ...)
  evaluate.load_run(run_dir) -> TrainedRun(model, variables, ...)
  render.render_cameras(model, variables, cameras) -> {"rgb", "depth", "accumulation", ...}
  evaluate.evaluate(model, variables, dataset) -> (metrics, renders)
"""
