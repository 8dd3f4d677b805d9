"""What the package writes to disk: atomic files and torn-line-tolerant logs (:mod:`.files`), and
checkpoints of a filter run (:mod:`.checkpoint`)."""
