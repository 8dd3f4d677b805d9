"""What a run shows: its figures (:mod:`.figures`), TensorBoard records (:mod:`.tensorboard`) and the statistics
of its tables (:mod:`.statistics`)."""
