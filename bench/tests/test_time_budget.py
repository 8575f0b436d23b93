from bench.time_budget import stage_rank, table


def test_stages_are_listed_coarse_to_fine_with_the_pixels_rendered_again_last():
    stages = ["grid 1", "rendered again", "grid 4", "level 0", "grid 2"]
    assert sorted(stages, key=stage_rank) == ["level 0", "grid 4", "grid 2", "grid 1", "rendered again"]


def test_the_table_gives_each_graph_its_distance_from_the_floor():
    results = {
        "threads": 2,
        "flops_per_sample": 300e3,
        "gemm_gflops": 150.0,
        "views": [
            {
                "scene": "scan37 32",
                "size": "640x512",
                "samples_per_pixel": 9.0,
                "samples_per_pixel_by_stage": {"level 0": 2.0, "grid 1": 7.0},
                "renderer_seconds": 12.0,
                "us_per_sample_by_graph": {"renderer_guide": 5.0, "renderer_fine": 3.0},
            }
        ],
    }
    text = table(results)
    assert "a floor of 2.00 us a sample" in text
    assert "level 0 2.00, grid 1 7.00 (9.00)" in text
    assert "5.00 (2.5x), 3.00 (1.5x)" in text
