"""The paper's experiments (``gpbf reproduce``: Tables 5-10, Figs 3-4) and the RL experiment."""
