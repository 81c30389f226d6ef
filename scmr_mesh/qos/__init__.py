"""Quality of service of the thesis (Eq 3.12-3.14), pure (no Zenoh, no rerun).

``metrics``     ToR, RoR, percentiles, failover and failback gaps, report summaries
``negotiator``  the request negotiator: priorities, admission, a bounded queue
"""
