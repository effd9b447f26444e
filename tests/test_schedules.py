"""Schedules against the closed forms written out in SPEC §1–2 (independent NumPy formulas)."""

import numpy as np
import pytest

from slotlifter_jax import defaults, schedules


@pytest.mark.parametrize("t", [0, 1, 2500, 9999, 10_000, 30_000, 77_777, 250_000])
def test_lr_factors_match_spec(t):
  backbone = schedules.backbone_lr_factor(t, floor=0.02, warmup_steps=10_000, decay_steps=50_000)
  head = schedules.head_lr_factor(t, floor=0.02, decay_steps=50_000)
  np.testing.assert_allclose(backbone, 0.02 + 0.98 * min(1, t / 10_000) * 0.5 ** (1.5 * t / 50_000),
                             rtol=1e-5)
  np.testing.assert_allclose(head, 0.02 + 0.98 * 0.5 ** (t / 50_000), rtol=1e-5)


@pytest.mark.parametrize("t", [0, 1, 7_500, 15_000, 29_999, 30_000, 100_000])
def test_keep_ratio_and_noise_match_spec(t):
  keep = schedules.keep_ratio(t, mask_max=0.99, anneal_steps=30_000)
  expected = 1 - (0.495 * np.cos(np.pi * t / 30_000) + 0.495) if t < 30_000 else 1.0
  np.testing.assert_allclose(keep, expected, atol=1e-6)
  sigma = schedules.slot_noise_sigma(t, anneal_steps=30_000)
  np.testing.assert_allclose(sigma, 0.5 * (1 + np.cos(np.pi * t / 30_000)) if t < 30_000 else 0.0,
                             atol=1e-6)


def test_endpoints_and_locality():
  np.testing.assert_allclose(schedules.keep_ratio(0, mask_max=0.99, anneal_steps=30_000), 0.01,
                             atol=1e-6)
  assert float(schedules.slot_noise_sigma(0, anneal_steps=30_000)) == 1.0
  assert bool(schedules.locality_on(49_999, steps=50_000))
  assert not bool(schedules.locality_on(50_000, steps=50_000))
  assert not bool(schedules.locality_on(0, steps=0))


def test_all_schedules_reports_every_value():
  c = defaults.base_config().train
  s = schedules.all_schedules(12_345, c)
  assert set(s) == {"lr_backbone", "lr_head", "keep_ratio", "slot_noise_sigma", "locality"}
  np.testing.assert_allclose(s["lr_head"], 5e-5 * (0.02 + 0.98 * 0.5 ** (12_345 / 50_000)),
                             rtol=1e-5)
