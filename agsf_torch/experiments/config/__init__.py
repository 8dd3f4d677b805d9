"""An experiment's configuration: the presets and their validation (:mod:`.loader`), and the filters, models and
loop options built from it (:mod:`.factories`)."""
