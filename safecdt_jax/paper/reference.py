"""The paper's evaluation numbers (Safe-CDT, section 5 and appendices C-D), shown beside ours.

Rows are (reward, reward std, cost, cost std, VR %, VR std) unless stated; B = 30 unless a
budget is given. Table 7 and the Table 1 / Table 4 Safe-CDT rows live with the baselines
(`safecdt_jax.baselines.job.PAPER_TABLE7`, `PAPER_SAFE_CDT`).
"""

from __future__ import annotations

# Table 1: Safe-CDT at B = 30 (CG1-CG2 15 seeds, the others 3).
TABLE1 = {"CG1-CG2": (-15.93, 2.01, 8.56, 2.21, 14.4, 6.3),
          "CC1-CC2": (0.77, 0.29, 9.05, 1.60, 24.7, 5.0),
          "PC1-PC2": (-12.32, 3.30, 19.21, 3.34, 56.0, 11.1)}

# Table 2: Safe-CDT on CG1-CG2 per budget (3 seeds).
TABLE2 = {25.0: (-13.91, 0.92, 8.17, 1.49, 24.7, 3.1),
          30.0: (-15.40, 2.99, 7.87, 0.67, 12.7, 3.1),
          35.0: (-15.71, 2.87, 10.56, 1.87, 14.0, 5.3),
          40.0: (-17.33, 0.26, 9.18, 2.56, 9.3, 4.2),
          50.0: (-14.88, 1.23, 11.40, 1.14, 10.0, 3.5)}

# Table 3: the variants on CG1-CG2 at B = 30 (3 seeds).
TABLE3 = {"safe_cdt": (-14.67, 0.97, 8.97, 1.49, 16.7, 5.8),
          "no_reweight": (-16.15, 1.67, 8.56, 0.44, 15.3, 2.3),
          "scheduler_only": (-14.97, 2.68, 8.41, 1.91, 14.0, 7.2),
          "zero_shot": (-14.74, 2.73, 8.09, 1.84, 15.6, 7.0),
          "naive_lora": (-16.47, 2.01, 8.38, 1.69, 14.8, 6.7)}

# Table 5: mean cost per CTG ratio (zero-shot, RTG ratio 0.5, 5 seeds x 50 episodes); the
# Spearman rho of cost against the ratio computed from these means (the text: CC 0.9, all > 0.5).
TABLE5 = {"CG1-CG2": {0.2: 7.74, 0.4: 8.17, 0.6: 7.42, 0.8: 9.45, 1.0: 9.08},
          "CC1-CC2": {0.2: 15.16, 0.4: 16.03, 0.6: 16.66, 0.8: 16.28, 1.0: 16.95},
          "PC1-PC2": {0.2: 27.17, 0.4: 28.04, 0.6: 27.78, 0.8: 27.45, 1.0: 28.74}}

# Table 6: step changes after episode 50 of 100 (5 seeds): (delta cost, its std, delta VR pp,
# seeds of 5 whose delta has the expected sign).
TABLE6 = {("CG1-CG2", "low->high"): (1.26, 1.18, 5.6, 4),
          ("CG1-CG2", "high->low"): (-0.63, 2.53, -2.8, 3),
          ("CC1-CC2", "low->high"): (1.64, 1.74, 4.4, 4),
          ("CC1-CC2", "high->low"): (-2.81, 1.64, -9.2, 5),
          ("PC1-PC2", "low->high"): (1.52, 1.82, 0.0, 4),
          ("PC1-PC2", "high->low"): (-2.32, 0.95, -5.2, 5)}
