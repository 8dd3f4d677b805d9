"""Running an experiment: the batched Monte Carlo loop (:mod:`.runner`, :mod:`.experiment`), recorded data
(:mod:`.recorded`), its outputs and their background writing (:mod:`.outputs`, :mod:`.file_writer`), worker
processes (:mod:`.worker_pool`), progress bars and the memory checks (:mod:`.progress`, :mod:`.resources`)."""
