"""The physics core: the model and its static topology, the internal array layout, argument checks, and
the stepping loops (`step`, `rollout`) that every solver plugs into, and the batch-minor layout behind
`batched_rollout`."""
