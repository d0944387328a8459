"""Alerting: exceedance, predicted exceedance, sudden change and stale alerts; the TRC plan."""
