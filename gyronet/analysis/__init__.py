"""Analysis: the tables (Table 1, real data, rates), the survey and the diagnosis loop.

The top layer: may import every other folder of gyronet.
"""
