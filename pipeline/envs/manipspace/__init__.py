"""OGBench's manipulation tasks (`ogbench.manipspace`: the cubes, the scene, the puzzles), in one
place: `env` (the env behind the `EnvSpec` interface, its tasks and success rule), `data` (its
`play` and `noisy` datasets made with OGBench's own oracles, and their check), `solver` (the
oracles on the evaluation tasks: `oposm oracle`)."""
