// Calls written against the client generated from /openapi.json (api.d.ts, made by the test):
// tsc must accept them, so other tools can bind to the API as published.
import createClient from "openapi-fetch";
import type { components, paths } from "./api";

type SuggestRequest = components["schemas"]["SuggestRequest"];
type ErrorResponse = components["schemas"]["ErrorResponse"];

const client = createClient<paths>({ baseUrl: "http://127.0.0.1:8000" });

export async function firstSuggestion(points: number[][]): Promise<string | undefined> {
  const body: SuggestRequest = { points, k: 5, category: ["chair"] };
  const { data, error } = await client.POST("/suggest", { body });
  if (error) {
    const refusal: ErrorResponse = error;
    throw new Error(`${refusal.error.code}: ${refusal.error.message}`);
  }
  const best = data.suggestions.at(0);
  const [x, y, z] = best?.translation ?? [0, 0, 0];
  return best ? `${best.rank} ${best.part_id} ${best.score.toFixed(1)} at ${x} ${y} ${z}` : undefined;
}

export async function partFaces(partId: string): Promise<number | undefined> {
  const { data } = await client.GET("/parts/{part_id}", { params: { path: { part_id: partId } } });
  return data?.n_faces;
}

export async function categories(): Promise<string[]> {
  const { data } = await client.GET("/categories");
  return (data ?? []).map((c) => `${c.name} (${c.parts})`);
}
