"""Dask executor for forestmap runs: dagster-dask's, with its step arguments packed.

dagster-dask (0.29) hands each step's arguments to ``Client.submit`` as they are; recent Dask
releases walk tuple arguments to find nested tasks, and Dagster's execution-state records for a
partitioned run refuse iteration ("Iteration is not allowed on `@record`
KeyRangesPartitionsSubset"), so every partitioned run fails before its first step. Here the
arguments travel pickled as one ``bytes`` value and are unpacked on the worker. dagster-dask also
names each Dask task ``<job>.<step>``; Dask treats tasks of one key as one, so two concurrent runs
of the same job (two scans) would share results: the task key here includes the run id.
Everything else (cluster selection, ``dagster-dask/resource_requirements`` tags, config schema)
is dagster-dask's.
"""

from __future__ import annotations

import cloudpickle
import dask.distributed
from dagster import ExecutorDefinition, multiple_process_executor_requirements
from dagster import _check as check
from dagster._core.errors import raise_execution_interrupts
from dagster._core.events import DagsterEvent
from dagster._core.execution.context.system import PlanOrchestrationContext
from dagster._core.execution.plan.plan import ExecutionPlan
from dagster._utils import iterate_with_context
from dagster_dask.executor import (
    DaskExecutor,
    dask_executor,
    get_dask_resource_requirements,
    query_on_dask_worker,
)


def _run_packed_step(dependencies, payload: bytes):
    """On the worker: unpack the step's arguments and execute it (``dependencies`` only orders
    the Dask tasks)."""
    return query_on_dask_worker(dependencies, *cloudpickle.loads(payload))


class PackedDaskExecutor(DaskExecutor):
    def execute(self, plan_context: PlanOrchestrationContext, execution_plan: ExecutionPlan):
        check.invariant(plan_context.instance.is_persistent, "Dask execution requires a persistent DagsterInstance")
        job_name = plan_context.job_name
        instance = plan_context.instance
        if self.cluster_type == "existing":
            cluster = self.cluster_configuration["address"]
        elif self.cluster_type == "local":
            cluster = dask.distributed.LocalCluster(**self.build_dict(job_name))
        else:  # the other cluster kinds exactly as dagster-dask builds them
            yield from super().execute(plan_context, execution_plan)
            return
        with dask.distributed.Client(cluster) as client:
            futures_by_step = {}
            futures = []
            for level in execution_plan.get_steps_to_execute_by_level():
                for step in level:
                    dependencies = [
                        futures_by_step[key] for step_input in step.step_inputs for key in step_input.dependency_keys
                    ]
                    payload = cloudpickle.dumps((
                        plan_context.reconstructable_job, plan_context.dagster_run, plan_context.run_config,
                        [step.key], instance.get_ref(), execution_plan.known_state,
                    ))
                    future = client.submit(
                        # the run id keeps concurrent runs of one job (one per scan) apart: Dask
                        # shares results between tasks of the same key
                        _run_packed_step, dependencies, payload,
                        key=f"{job_name}.{plan_context.dagster_run.run_id}.{step.key}",
                        resources=get_dask_resource_requirements(step.tags),
                    )
                    futures.append(future)
                    futures_by_step[step.key] = future
            completed = dask.distributed.as_completed(futures, with_results=True)
            for _, result in iterate_with_context(raise_execution_interrupts, completed):
                for event in result:
                    yield check.inst(event, DagsterEvent)


def _create(init_context):
    ((cluster_type, cluster_configuration),) = init_context.executor_config["cluster"].items()
    return PackedDaskExecutor(cluster_type, cluster_configuration)


packed_dask_executor = ExecutorDefinition(
    name="dask",
    config_schema=dask_executor.config_schema,
    requirements=multiple_process_executor_requirements(),
    executor_creation_fn=_create,
    description="dagster-dask's executor (same configuration), robust to partitioned runs.",
)
