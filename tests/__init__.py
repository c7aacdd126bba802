"""The tests of torchrl-dhrl; the folders mirror the package (``tests/planner/test_graph.py`` tests
``torchrl_dhrl/planner/graph.py``), ``tests/envs`` the environments installed as ``torchrl_dhrl.envs``."""
