"""gymnasium-robotics' PointMazes (the refactored D4RL maze2d), in one place: `env` (the env, its
point-mass physics and layout), `expert` (the scripted waypoint expert), `generate` (its
demonstrations, made the way D4RL made maze2d) and `checks` (a maze dataset's sanity checks).
OGBench's mazes are `pipeline.envs.ogbench`; the MuJoCo state all envs share,
`pipeline.envs.physics`."""
