"""MIT-mode actuators (CubeMars/T-Motor AK, Damiao, Mini-Cheetah firmware): codec, model table, drive."""
