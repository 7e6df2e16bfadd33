"""Which tests are `slow` and which start a simulator (`sim`): one table, applied at collection by
tests/conftest.py, so that a test's marker sits next to the reason and its measured time.

`slow`: over 5 s on 2 CPU cores (setup included: a module fixture that trains counts against the
tests that use it), as measured by `pytest --durations=0`. `make test-fast` (pytest -m "not slow")
leaves them out; `make test` runs everything.

`sim`: starts a simulator (gym-pusht, robosuite or Meta-World: the sim extra).

A name is FILE::TEST (the file's name, not its folder; TEST without parameters) or FILE alone for
every test in it. A name that no longer matches a collected test is an error (see conftest.py),
so the table cannot silently go stale when a test is renamed.
"""

from __future__ import annotations

# in order of their time, the longest first: under pytest-xdist their files are handed out first
# (slow_files_first), so that no long file starts last and runs alone at the end
SLOW = [
    # a whole study (ingest, train, 2 rounds x 3 variants, sweeps, rollouts) as child processes
    "test_reflow_rounds.py::test_tiny_study_builds_every_row_and_reports_it",
    "test_reflow_rounds.py::test_base_from_continues_a_checkpoint_of_the_same_run_only",
    # the catalogues: each module fixture runs every case through the CLI (40-140 s)
    "test_artifact_catalogue.py",
    "test_convert_catalogue.py",
    "test_bad_input_catalogue.py",
    # LeRobot Push-T with its camera from ingest to an ONNX export
    "test_lerobot_camera_chain.py",
    # trainings, torchrun and signals in child processes
    "test_workspace.py::test_resume_after_sigint_continues_from_the_last_checkpoint",
    "test_devices.py",
    "test_training.py",
    "test_lerobot_reader_faults.py::test_tasks_table_written_by_pandas_with_the_task_as_index",
    "test_messages.py::test_ctrl_c_in_reflow_keeps_its_finished_blocks_and_the_next_run_reuses_them",
    "test_export.py::test_image_policy_exports_with_its_encoder",
    "test_export.py::test_the_tolerance_flag_sets_the_bound_and_is_range_checked",
    "test_stage_costs.py::test_bookkeeping_changes_retrain_nothing_and_more_steps_continue",
    "test_stage_costs.py::test_each_stage_announces_its_cost_and_steps_have_flags",
    "test_lift_expert.py",
    # reflow, align and distill killed (children) or interrupted at each commit point, then rerun
    "test_stage_commit_points.py",
    # a tiny flow trained, reflow stopped after 3 of 4 blocks, then 5 reruns on damaged blocks
    "test_reflow_blocks.py",
    # Meta-World episodes, and collects killed at their commit points in child processes
    "test_collect_file.py",
    # the demo at a tiny size, twice, in child processes (45 s of CPU; 3 min on a loaded machine)
    "test_demo.py::test_the_demo_compares_the_student_with_one_euler_step_under_both_executions",
    "test_demo.py::test_the_demo_prints_only_sefas_lines",
    "test_reflow_progress.py",
    "test_processor.py::test_a_large_camera_is_resized_to_a_model_size_everywhere",
    "test_readme_commands.py::test_readme_deploy_snippets_run_as_written_on_store_keys",
    "test_sefa_stages.py::test_a_run_stopped_along_a_longer_schedule_is_that_schedules_checkpoint",
    "test_convert_safety.py::test_ctrl_c_and_sigterm_stop_a_hung_encoder",
    "test_serve_openpi.py",
    # from a run of the rest (-m "not slow" -n 2 --durations=60) on a loaded machine, each over
    # 20 s there (about 5x a quiet machine's time): whole files where a module or session
    # fixture trains or exports for most of their tests
    "test_pipeline.py",
    "test_export.py",
    "test_lerobot_export.py",
    "test_serve.py",
    "test_serve_busy.py",
    "test_device_batches.py",
    "test_bench_latency.py",
    "test_bench_data.py",
    "test_sefa_stages.py",
    "test_methods.py",
    "test_finite.py",
    "test_diffusion.py::test_ddpm_training_on_pusht_learns_and_records_its_convention",
    "test_diffusion.py::test_ddpm_policy_samples_with_ddpm_and_ddim_and_refuses_ode_solvers",
    "test_diffusion.py::test_reflow_refuses_a_diffusion_checkpoint",
    "test_diffusion.py::test_cli_trains_the_baseline_with_objective_flag_and_evaluates_ddim",
    "test_messages.py::test_a_busy_machine_is_said_when_training_starts",
    "test_messages.py::test_piped_progress_says_when_the_loss_was_measured",
    "test_messages.py::test_a_finished_offline_solve_ends_at_its_end",
    "test_messages.py::test_results_show_rollout_nfe_and_whole_folder_names",
    "test_messages.py::test_status_during_a_run_shows_no_numbers_of_the_old_run",
    "test_messages.py::test_a_warmup_longer_than_the_run_is_said_naming_both",
    "test_messages.py::test_ctrl_c_says_what_was_kept_and_resume_makes_one_whole_run",
    "test_messages.py::test_ctrl_c_in_a_tee_pipeline_still_exits_130_and_keeps_the_run",
    "test_convert_safety.py::test_a_rerun_after_kill_9_leaves_no_debris",
    "test_config_safety.py::test_train_out_uses_the_workspace_settings_and_says_which_keys_it_sees",
    "test_readme_commands.py::test_exports_record_their_checkpoint_and_status_shows_a_stale_one",
    "test_ingest.py::test_pusht_ingests_all_206_episodes_and_opens_as_plain_dp_zarr",
    "test_ingest.py::test_pusht_reingest_is_skipped",
    "test_ingest.py::test_inspect_store_json",
    "test_sampler.py::test_pusht_batch_equals_stacked_windows",
    "test_sampler.py::test_pusht_windows_per_episode_and_no_crossing",
    "test_sampler.py::test_to_torch_shapes_dtypes_range",
    # rollouts of a flow and a student for the comparison; a camera flow's offline evaluation
    "test_comparison.py::test_compare_agrees_with_paired_evals_on_the_same_logs",
    "test_comparison.py::test_results_prints_the_comparison_under_its_list",
    "test_offline_spread.py",
    "test_readme_commands.py::test_readme_small_run_is_cpu_sized_on_a_camera_store",
    "test_pipeline.py::test_run_says_what_alignment_did_as_align_does",
    "test_rollout_progress.py",
]

SIM = [
    "test_image_rollouts.py",
    "test_collect_file.py",
    "test_demo.py::test_the_demo_compares_the_student_with_one_euler_step_under_both_executions",
    "test_demo.py::test_the_demo_prints_only_sefas_lines",
    "test_demo.py::test_robosuites_start_up_notes_are_filtered_and_its_errors_kept",
    "test_reflow_progress.py",
    "test_lift_expert.py",
    "test_metaworld.py",
    "test_pusht_env.py",
    "test_lerobot_camera_chain.py",
    "test_reflow_rounds.py::test_tiny_study_builds_every_row_and_reports_it",
    "test_messages.py::test_results_show_rollout_nfe_and_whole_folder_names",
    "test_workspace.py::test_eval_is_cached_and_kept_apart_by_settings",
    "test_workspace.py::test_progress_lines_in_piped_output",
    "test_devices.py::test_every_stage_takes_device_and_refuses_a_missing_gpu",
    "test_devices.py::test_torchrun_rollouts_split_the_seeds_and_match_one_process",
    "test_training.py::test_pusht_rollout_eval_is_valid_and_reproducible",
    "test_comparison.py::test_compare_agrees_with_paired_evals_on_the_same_logs",
    "test_comparison.py::test_results_prints_the_comparison_under_its_list",
    "test_rollout_progress.py",
]


def names(item) -> tuple[str, str]:
    """The two names an item answers to in the tables: FILE and FILE::TEST."""
    file = item.path.name
    return file, f"{file}::{getattr(item, 'originalname', item.name)}"


def apply(items, mark_slow, mark_sim) -> set[str]:
    """Mark the collected items; return the table's names that matched none of them but whose
    FILE was collected (a renamed or removed test)."""
    used, files = set(), set()
    for item in items:
        file, full = names(item)
        files.add(file)
        for table, mark in ((SLOW, mark_slow), (SIM, mark_sim)):
            hit = {file, full} & set(table)
            if hit:
                item.add_marker(mark)
                used |= hit
    return {n for n in SLOW + SIM if n.split("::")[0] in files and n not in used}


def rank(file: str) -> int:
    """A test file's place in SLOW (by its name; FILE or FILE::TEST), after them the rest."""
    name = file.rsplit("/", 1)[-1]
    return next((i for i, n in enumerate(SLOW) if n.split("::")[0] == name), len(SLOW))


def slow_files_first(scheduler_class):
    """pytest-xdist's file scheduler (`--dist loadfile`), handing out the files of SLOW first,
    longest first: xdist's own order is by number of tests, which started the 3-test file of
    the 5-minute study last and left it running alone at the end."""
    class SlowFilesFirst(scheduler_class):
        def _assign_work_unit(self, node):
            # the base class hands out the queue's first file: put the slowest one there
            first = min(self.workqueue, key=rank)
            self.workqueue.move_to_end(first, last=False)
            super()._assign_work_unit(node)
    return SlowFilesFirst
