"""The simulate stage's library: one condition's media observed by every sensor of a dataset, as a weather copy.

- `media`: the resolved media of a condition (tuned fog levels, per-scene particle fields) and `SceneMedia`;
- `observe`: the pure core, ``observe(frame, images, ranges, media, sensors, airlight, options, lidar)`` ->
  `FrameWeather`;
- `plan`: the jobs (samples with their scene's media and airlight);
- `weather_copy`: inputs, outputs, resume records and the completed nuScenes-format copy.

Import the submodules directly: a stage imports only the code it declares in dvc.yaml.
"""
