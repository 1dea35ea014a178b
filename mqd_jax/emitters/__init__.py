"""Search components: the baseline emitters (uniform, iso+line), acquisition rules, steering, pursuit, the model
emitter, imagination, and the presets. Imports `core` and `surrogate`."""
