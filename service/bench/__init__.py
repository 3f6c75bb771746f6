"""``pitune bench``: load benchmark of the tuner daemon over Zenoh on loopback.

The command starts a tuner daemon (``pitune tuner``) as a child process with a fresh
database, registers N loops over the REST API (``POST /loops/bulk``), then becomes the
load generator: N FOPTD plants under PI control (:class:`plant_sim.FOPTDBatch` and
:class:`plant_sim.PIBatch`, vectorised), sampled in real time at ``--rate`` per loop,
publishing their samples over Zenoh (batched ``{prefix}/samples`` messages, as a
gateway fronting many loops would, or one message per sample with ``--per-loop``) and
applying the gains the tuner sends back (bumplessly, between samples). The loops are
registered with ``gateway: "bench"``, so their gains come batched on
``{prefix}/gateways/bench/gains``; with ``--per-loop`` or ``--per-loop-gains`` they are
registered without one and get a message each on ``{prefix}/loops/{id}/gains``.

Sample clocks are spread: the loops are split into phase groups ``--tick`` apart, so
at 1 Hz and 10 ms ticks every 10 ms one hundredth of the loops is sampled, and their
RL periods differ (plant time constants are drawn from ``--tau``), so RL steps are
spread too. ``--aligned`` is the worst case: every loop is sampled at the same instant
and has the same RL period, so all N loops fall due in the same sample.

Measured over a steady window (``--duration`` seconds after ``--warmup``):

* samples published per second (generator) and accepted per second (daemon metrics);
  samples lost (published minus received once the daemon drained) and rejected, both
  over the whole run: they must be zero;
* update latency: from the wall time the generator published the sample that
  completed an RL step to the arrival of the gains message for it (matched by loop and
  the sample's plant time ``t``, which gains messages carry): p50, p99, max;
* the daemon's CPU use and RSS (``/proc``), the generator's CPU use, and the RSS per
  loop (growth from registering 1,000 to registering all N loops, divided);
* the batched inference step for N due loops, timed in this process on one thread,
  for ``agent.act`` and the daemon's :class:`service.agent.fast.FastPolicy`.

It prints a table and writes the JSON to ``benchmarks/results/``. Modules: ``config``
(the settings), ``fleet`` (the simulated loops), ``load`` (the run), ``probes``
(metrics, CPU), ``inference`` (the in-process timing), ``report``, ``command`` (CLI).
"""

from service.bench.command import add_arguments, run

__all__ = ["add_arguments", "run"]
