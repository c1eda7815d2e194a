"""Vehicle physics shared by the safety mask, the scenario generator and the rule-based baselines (IDM)."""
